"""_native.dlpack_capsule: raw memory as a DLPack capsule that keeps its owner alive.

CPU only (device_type 1, kDLCPU): numpy is the consumer here; torch and cupy read the same
capsules. The struct layout is checked through ctypes against DLPack 1.0's dlpack.h.
"""
import ctypes
import gc
import subprocess
import sys
import threading
import weakref

import numpy as np
import pytest

from rosidl_buffer_py._native import dlpack_capsule

KDLCPU = 1


class Owner:
    """What keeps the memory alive (weak-referenceable, unlike a numpy array)."""

    def __init__(self, nbytes=256):
        self.array = np.arange(nbytes, dtype=np.uint8)

    @property
    def address(self):
        return self.array.ctypes.data


class Holder:
    """The object numpy.from_dlpack wants: ``__dlpack__`` and ``__dlpack_device__``.

    Exports a versioned capsule when the consumer asks with ``max_version`` (1, x), unless
    ``versioned`` forces one form."""

    def __init__(self, owner, versioned=None, readonly=False, nbytes=None):
        self.owner = owner
        self.versioned = versioned
        self.readonly = readonly
        self.nbytes = owner.array.nbytes if nbytes is None else nbytes
        self.asked = None
        self.exported_versioned = None

    def __dlpack__(self, *, stream=None, max_version=None, dl_device=None, copy=None):
        self.asked = max_version
        versioned = self.versioned
        if versioned is None:
            versioned = max_version is not None and max_version[0] >= 1
        self.exported_versioned = versioned
        return dlpack_capsule(self.owner.address, self.nbytes, KDLCPU, 0, self.owner,
                              versioned=versioned, readonly=self.readonly)

    def __dlpack_device__(self):
        return (KDLCPU, 0)


# ctypes mirror of dlpack.h v1.0, to read what the capsule holds
class DLDevice(ctypes.Structure):
    _fields_ = [('device_type', ctypes.c_int32), ('device_id', ctypes.c_int32)]


class DLDataType(ctypes.Structure):
    _fields_ = [('code', ctypes.c_uint8), ('bits', ctypes.c_uint8), ('lanes', ctypes.c_uint16)]


class DLTensor(ctypes.Structure):
    _fields_ = [('data', ctypes.c_void_p), ('device', DLDevice), ('ndim', ctypes.c_int32),
                ('dtype', DLDataType), ('shape', ctypes.POINTER(ctypes.c_int64)),
                ('strides', ctypes.POINTER(ctypes.c_int64)), ('byte_offset', ctypes.c_uint64)]


Deleter = ctypes.CFUNCTYPE(None, ctypes.c_void_p)  # a C call: ctypes releases the GIL


class DLManagedTensor(ctypes.Structure):
    _fields_ = [('dl_tensor', DLTensor), ('manager_ctx', ctypes.c_void_p),
                ('deleter', ctypes.c_void_p)]


class DLPackVersion(ctypes.Structure):
    _fields_ = [('major', ctypes.c_uint32), ('minor', ctypes.c_uint32)]


class DLManagedTensorVersioned(ctypes.Structure):
    _fields_ = [('version', DLPackVersion), ('manager_ctx', ctypes.c_void_p),
                ('deleter', ctypes.c_void_p), ('flags', ctypes.c_uint64),
                ('dl_tensor', DLTensor)]


_get_pointer = ctypes.pythonapi.PyCapsule_GetPointer
_get_pointer.restype = ctypes.c_void_p
_get_pointer.argtypes = [ctypes.py_object, ctypes.c_char_p]
_set_name = ctypes.pythonapi.PyCapsule_SetName
_set_name.restype = ctypes.c_int
_set_name.argtypes = [ctypes.py_object, ctypes.c_char_p]
# the capsule keeps the name's pointer: these bytes live as long as the module
USED_NAMES = {b'dltensor': b'used_dltensor', b'dltensor_versioned': b'used_dltensor_versioned'}


def managed_tensor(capsule, name):
    struct = DLManagedTensorVersioned if name == b'dltensor_versioned' else DLManagedTensor
    return struct.from_address(_get_pointer(capsule, name))


def consume(capsule, name):
    """Take the managed tensor as a consumer does: rename the capsule, return the tensor."""
    managed = managed_tensor(capsule, name)
    assert _set_name(capsule, USED_NAMES[name]) == 0
    return managed


def test_numpy_reads_the_same_memory():
    owner = Owner()
    array = np.from_dlpack(Holder(owner))
    assert array.dtype == np.uint8 and array.shape == (256,)
    assert array.tobytes() == bytes(range(256))
    assert np.shares_memory(array, owner.array)
    array[3] = 200  # writes through to the owner's memory
    assert owner.array[3] == 200
    owner.array[4] = 201
    assert array[4] == 201


@pytest.mark.parametrize('versioned', [False, True])
def test_owner_lives_as_long_as_the_consumer_array(versioned):
    owner = Owner()
    gone = weakref.ref(owner)
    array = np.from_dlpack(Holder(owner, versioned=versioned))
    del owner
    gc.collect()
    assert gone() is not None  # only the consumer's array keeps it now
    assert array[255] == 255
    del array
    gc.collect()
    assert gone() is None


@pytest.mark.parametrize('versioned', [False, True])
def test_unconsumed_capsule_releases_its_owner(versioned):
    owner = Owner()
    gone = weakref.ref(owner)
    capsule = dlpack_capsule(owner.address, 256, KDLCPU, 0, owner, versioned=versioned)
    del owner
    gc.collect()
    assert gone() is not None
    del capsule
    gc.collect()
    assert gone() is None


@pytest.mark.parametrize('versioned', [False, True])
def test_deleter_runs_exactly_once(versioned):
    owner = Owner()
    start = sys.getrefcount(owner)
    capsule = dlpack_capsule(owner.address, 256, KDLCPU, 0, owner, versioned=versioned)
    assert sys.getrefcount(owner) == start + 1
    del capsule
    assert sys.getrefcount(owner) == start
    # consumed: numpy's deleter call, then the renamed capsule's destructor (a no-op)
    array = np.from_dlpack(Holder(owner, versioned=versioned))
    assert sys.getrefcount(owner) == start + 1
    del array
    gc.collect()
    assert sys.getrefcount(owner) == start


def test_versioned_when_numpy_asks_for_it():
    owner = Owner()
    holder = Holder(owner)
    array = np.from_dlpack(holder)
    if np.lib.NumpyVersion(np.__version__) >= '2.1.0':
        assert holder.asked is not None and holder.asked[0] == 1
        assert holder.exported_versioned
    assert array.flags.writeable
    assert array.tobytes() == bytes(range(256))


def test_readonly_gives_a_read_only_array():
    owner = Owner()
    array = np.from_dlpack(Holder(owner, versioned=True, readonly=True))
    assert not array.flags.writeable
    with pytest.raises(ValueError):
        array[0] = 1
    assert np.shares_memory(array, owner.array)


def test_readonly_needs_versioned():
    owner = Owner()
    with pytest.raises(ValueError, match='versioned'):
        dlpack_capsule(owner.address, 256, KDLCPU, 0, owner, readonly=True)


def test_zero_bytes():
    owner = Owner()
    array = np.from_dlpack(Holder(owner, nbytes=0))
    assert array.shape == (0,) and array.dtype == np.uint8
    # NULL is fine when there is nothing to read
    capsule = dlpack_capsule(0, 0, KDLCPU, 0, None)
    assert managed_tensor(capsule, b'dltensor').dl_tensor.shape[0] == 0


@pytest.mark.parametrize('versioned, readonly', [(False, False), (True, False), (True, True)])
def test_struct_layout(versioned, readonly):
    owner = Owner()
    capsule = dlpack_capsule(owner.address, 256, 2, 3, owner, versioned=versioned,
                             readonly=readonly)
    name = b'dltensor_versioned' if versioned else b'dltensor'
    managed = managed_tensor(capsule, name)
    tensor = managed.dl_tensor
    assert tensor.data == owner.address
    assert (tensor.device.device_type, tensor.device.device_id) == (2, 3)
    assert tensor.ndim == 1
    assert (tensor.dtype.code, tensor.dtype.bits, tensor.dtype.lanes) == (1, 8, 1)
    assert tensor.shape[0] == 256
    assert not tensor.strides  # NULL: compact
    assert tensor.byte_offset == 0
    assert managed.deleter
    if versioned:
        assert (managed.version.major, managed.version.minor) == (1, 0)
        assert managed.flags == (1 if readonly else 0)


@pytest.mark.parametrize('versioned', [False, True])
def test_deleter_from_another_thread_without_the_gil(versioned):
    owner = Owner()
    start = sys.getrefcount(owner)
    gone = weakref.ref(owner)
    capsule = dlpack_capsule(owner.address, 256, KDLCPU, 0, owner, versioned=versioned)
    managed = consume(capsule, b'dltensor_versioned' if versioned else b'dltensor')
    del capsule  # renamed: its destructor leaves the tensor to us
    gc.collect()
    assert sys.getrefcount(owner) == start + 1
    deleter = Deleter(managed.deleter)
    address = ctypes.addressof(managed)
    del managed
    thread = threading.Thread(target=deleter, args=(address,))
    thread.start()
    thread.join()
    assert sys.getrefcount(owner) == start
    del owner
    gc.collect()
    assert gone() is None


@pytest.mark.parametrize('kwargs, value', [
    ({'address': -1}, '-1'),
    ({'address': 2 ** 64}, str(2 ** 64)),
    ({'nbytes': -5}, '-5'),
    ({'device_type': 0}, '0'),
    ({'device_type': 4}, '4'),
    ({'device_type': 2 ** 40}, str(2 ** 40)),
    ({'device_id': -1}, '-1'),
    ({'address': 0, 'nbytes': 16}, '16'),
])
def test_bad_arguments_raise_value_error(kwargs, value):
    owner = Owner()
    args = {'address': owner.address, 'nbytes': 256, 'device_type': KDLCPU, 'device_id': 0,
            'owner': owner, **kwargs}
    start = sys.getrefcount(owner)
    with pytest.raises(ValueError) as error:
        dlpack_capsule(**args)
    assert value in str(error.value)
    if 'device_type' in kwargs:
        assert 'kDLCPU' in str(error.value) and 'kDLCUDA' in str(error.value)
    del error
    assert sys.getrefcount(owner) == start  # nothing held on failure


def test_non_int_arguments_raise_type_error():
    owner = Owner()
    with pytest.raises(TypeError):
        dlpack_capsule(float(owner.address), 256, KDLCPU, 0, owner)
    with pytest.raises(TypeError):
        dlpack_capsule(owner.address, '256', KDLCPU, 0, owner)


def test_capsules_alive_at_exit_do_not_crash():
    """Destroyed during finalization: the owner reference is leaked, nothing crashes."""
    code = (
        'import numpy as np\n'
        'from rosidl_buffer_py._native import dlpack_capsule\n'
        'a = np.arange(64, dtype=np.uint8)\n'
        'kept = [dlpack_capsule(a.ctypes.data, 64, 1, 0, a, versioned=v) for v in (0, 1)]\n'
        'print("ok")\n')
    result = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                            timeout=60)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == 'ok'
