// dlpack_capsule: raw memory (a host pointer, or a device pointer on a GPU) as a DLPack
// capsule, so that torch/cupy/numpy.from_dlpack take it without a copy.
//
// The capsule describes a compact 1-D uint8 tensor of `nbytes` at `address`. Its managed
// tensor holds a strong reference to `owner` (whatever keeps the memory alive) until the
// consumer calls the deleter, or, if nobody consumed it, until the capsule is destroyed.
// Consumers may call the deleter from any thread, with or without the GIL.
#include "dlpack_export.hpp"

#include <cstdint>
#include <cstdlib>
#include <type_traits>

#include "py_glue.hpp"

namespace
{

// The DLPack ABI (dlpack.h, v1.0), declared here rather than vendoring the header: only the
// structs and constants this file fills in.
enum : int32_t {kDLCPU = 1, kDLCUDA = 2, kDLCUDAHost = 3};
enum : uint8_t {kDLUInt = 1};
constexpr uint64_t kDLPackFlagReadOnly = 1ULL << 0;  // DLPACK_FLAG_BITMASK_READ_ONLY
constexpr uint32_t kDLPackMajor = 1;
constexpr uint32_t kDLPackMinor = 0;

struct DLDevice
{
  int32_t device_type;  // an enum in dlpack.h: int-sized
  int32_t device_id;
};

struct DLDataType
{
  uint8_t code;
  uint8_t bits;
  uint16_t lanes;
};

struct DLTensor
{
  void * data;
  DLDevice device;
  int32_t ndim;
  DLDataType dtype;
  int64_t * shape;
  int64_t * strides;  // NULL: compact, row-major
  uint64_t byte_offset;
};

struct DLManagedTensor
{
  DLTensor dl_tensor;
  void * manager_ctx;
  void (* deleter)(DLManagedTensor * self);
};

struct DLPackVersion
{
  uint32_t major;
  uint32_t minor;
};

struct DLManagedTensorVersioned
{
  DLPackVersion version;
  void * manager_ctx;
  void (* deleter)(DLManagedTensorVersioned * self);
  uint64_t flags;
  DLTensor dl_tensor;
};

// Capsule names of the protocol: a consumer renames the capsule to "used_..." once it owns
// the managed tensor (then the capsule's destructor must not call the deleter).
constexpr const char * kUnversionedName = "dltensor";
constexpr const char * kVersionedName = "dltensor_versioned";

/// One allocation per export: the managed tensor, its shape and the owner reference.
/// malloc'ed, not PyMem: it is freed even when the interpreter is gone.
template<typename Managed>
struct Export
{
  Managed managed;
  int64_t shape[1];
  PyObject * owner;  // strong reference
};

bool interpreter_gone()
{
#if PY_VERSION_HEX >= 0x030D0000
  return !Py_IsInitialized() || Py_IsFinalizing();
#else
  return !Py_IsInitialized() || _Py_IsFinalizing();
#endif
}

/// The deleter consumers call (any thread, GIL held or not): drop the owner, free the export.
template<typename Managed>
void delete_export(Managed * managed)
{
  auto * exp = static_cast<Export<Managed> *>(managed->manager_ctx);
  // During or after finalization the GIL cannot be taken safely: leak the owner (the process
  // is ending) rather than crash or hang.
  if (!interpreter_gone()) {
    const PyGILState_STATE gil = PyGILState_Ensure();
    Py_XDECREF(exp->owner);
    PyGILState_Release(gil);
  }
  std::free(exp);
}

/// The capsule's destructor: the deleter runs only if no consumer took the tensor.
template<typename Managed>
void capsule_destructor(PyObject * capsule)
{
  const char * name =
    std::is_same_v<Managed, DLManagedTensorVersioned> ? kVersionedName : kUnversionedName;
  if (!PyCapsule_IsValid(capsule, name)) {
    return;  // renamed "used_...": the consumer owns it and calls the deleter itself
  }
  rbpy_glue::SavedException saved;  // may run while an exception is being raised
  auto * managed = static_cast<Managed *>(PyCapsule_GetPointer(capsule, name));
  if (managed != nullptr && managed->deleter != nullptr) {
    managed->deleter(managed);
  }
  PyErr_Clear();  // nothing to report from here; SavedException restores the earlier one
}

/// A new managed tensor of `Managed` (DLManagedTensor or ...Versioned) wrapped in its capsule.
template<typename Managed>
PyObject * make_capsule(
  uintptr_t address, int64_t nbytes, int32_t device_type, int32_t device_id, PyObject * owner,
  uint64_t flags)
{
  auto * exp = static_cast<Export<Managed> *>(std::calloc(1, sizeof(Export<Managed>)));
  if (exp == nullptr) {
    return PyErr_NoMemory();
  }
  exp->shape[0] = nbytes;
  DLTensor & tensor = exp->managed.dl_tensor;
  tensor.data = reinterpret_cast<void *>(address);
  tensor.device = {device_type, device_id};
  tensor.ndim = 1;
  tensor.dtype = {kDLUInt, 8, 1};
  tensor.shape = exp->shape;
  tensor.strides = nullptr;
  tensor.byte_offset = 0;
  exp->managed.manager_ctx = exp;
  exp->managed.deleter = delete_export<Managed>;
  if constexpr (std::is_same_v<Managed, DLManagedTensorVersioned>) {
    exp->managed.version = {kDLPackMajor, kDLPackMinor};
    exp->managed.flags = flags;
  }
  Py_INCREF(owner);
  exp->owner = owner;
  const char * name =
    std::is_same_v<Managed, DLManagedTensorVersioned> ? kVersionedName : kUnversionedName;
  PyObject * capsule = PyCapsule_New(&exp->managed, name, capsule_destructor<Managed>);
  if (capsule == nullptr) {
    Py_DECREF(owner);
    std::free(exp);
  }
  return capsule;
}

/// `value` as an exact int (anything with __index__): a new reference, or nullptr with
/// TypeError.
PyObject * as_index(PyObject * value, const char * what)
{
  if (!PyIndex_Check(value)) {
    PyErr_Format(
      PyExc_TypeError, "%s must be an int, got %.100s", what, Py_TYPE(value)->tp_name);
    return nullptr;
  }
  return PyNumber_Index(value);
}

/// The int `value` as a long long in [low, high]; false with ValueError naming the value and
/// `accepted` otherwise (or TypeError when it is no int).
bool int_in_range(
  PyObject * value, const char * what, long long low, long long high, const char * accepted,
  long long * out)
{
  PyObject * index = as_index(value, what);
  if (index == nullptr) {
    return false;
  }
  int overflow = 0;
  const long long v = PyLong_AsLongLongAndOverflow(index, &overflow);
  if (overflow == 0 && v == -1 && PyErr_Occurred()) {
    Py_DECREF(index);
    return false;
  }
  if (overflow != 0 || v < low || v > high) {
    PyErr_Format(PyExc_ValueError, "%s must be %s, got %S", what, accepted, index);
    Py_DECREF(index);
    return false;
  }
  Py_DECREF(index);
  *out = v;
  return true;
}

/// The int `value` as a pointer-sized address; false with ValueError (negative, too large).
bool address_value(PyObject * value, uintptr_t * out)
{
  PyObject * index = as_index(value, "address");
  if (index == nullptr) {
    return false;
  }
  int overflow = 0;
  const long long sign = PyLong_AsLongLongAndOverflow(index, &overflow);
  bool bad = overflow < 0 || (overflow == 0 && sign < 0);
  unsigned long long v = 0;
  if (!bad) {
    v = PyLong_AsUnsignedLongLong(index);
    bad = (v == static_cast<unsigned long long>(-1) && PyErr_Occurred()) || v > UINTPTR_MAX;
  }
  if (bad) {
    PyErr_Clear();  // OverflowError of a too large int: the ValueError below says it all
    PyErr_Format(
      PyExc_ValueError, "address must be an int in 0 .. %llu (a pointer), got %S",
      static_cast<unsigned long long>(UINTPTR_MAX), index);
    Py_DECREF(index);
    return false;
  }
  Py_DECREF(index);
  *out = static_cast<uintptr_t>(v);
  return true;
}

PyObject * dlpack_capsule(PyObject *, PyObject * args, PyObject * kwds)
{
  static const char * kwlist[] = {
    "address", "nbytes", "device_type", "device_id", "owner", "versioned", "readonly", nullptr};
  PyObject * address_obj;
  PyObject * nbytes_obj;
  PyObject * device_type_obj;
  PyObject * device_id_obj;
  PyObject * owner;
  int versioned = 0;
  int readonly = 0;
  if (!PyArg_ParseTupleAndKeywords(
      args, kwds, "OOOOO|pp:dlpack_capsule", const_cast<char **>(kwlist), &address_obj,
      &nbytes_obj, &device_type_obj, &device_id_obj, &owner, &versioned, &readonly))
  {
    return nullptr;
  }
  uintptr_t address = 0;
  long long nbytes = 0;
  long long device_type = 0;
  long long device_id = 0;
  if (!address_value(address_obj, &address) ||
    !int_in_range(nbytes_obj, "nbytes", 0, INT64_MAX, "an int >= 0", &nbytes) ||
    !int_in_range(
      device_type_obj, "device_type", kDLCPU, kDLCUDAHost,
      "1 (kDLCPU), 2 (kDLCUDA) or 3 (kDLCUDAHost)", &device_type) ||
    !int_in_range(device_id_obj, "device_id", 0, INT32_MAX, "an int in 0 .. 2**31-1", &device_id))
  {
    return nullptr;
  }
  if (address == 0 && nbytes > 0) {
    PyErr_Format(
      PyExc_ValueError, "address 0 (NULL) is accepted only with nbytes 0, got nbytes %lld",
      nbytes);
    return nullptr;
  }
  if (static_cast<unsigned long long>(nbytes) > UINTPTR_MAX - address) {
    PyErr_Format(
      PyExc_ValueError, "address + nbytes must fit in a pointer, got address %S, nbytes %lld",
      address_obj, nbytes);
    return nullptr;
  }
  // An unversioned capsule has no flags: the consumer would take the memory as writable.
  if (readonly && !versioned) {
    PyErr_SetString(
      PyExc_ValueError,
      "readonly=True needs versioned=True (DLPack >= 1.0): an unversioned capsule cannot "
      "mark the memory read-only");
    return nullptr;
  }
  const auto type = static_cast<int32_t>(device_type);
  const auto id = static_cast<int32_t>(device_id);
  if (versioned) {
    return make_capsule<DLManagedTensorVersioned>(
      address, nbytes, type, id, owner, readonly ? kDLPackFlagReadOnly : 0);
  }
  return make_capsule<DLManagedTensor>(address, nbytes, type, id, owner, 0);
}

PyMethodDef dlpack_functions[] = {
  RBPY_FUNCTION(dlpack_capsule, METH_VARARGS | METH_KEYWORDS,
    "dlpack_capsule(address, nbytes, device_type, device_id, owner, versioned=False, "
    "readonly=False)\n--\n\n"
    "A DLPack capsule ('dltensor', or 'dltensor_versioned' when versioned) of a compact 1-D "
    "uint8 tensor of nbytes at address on (device_type, device_id): 1 kDLCPU, 2 kDLCUDA, "
    "3 kDLCUDAHost. It holds a reference to owner until the consumer's deleter runs (or the "
    "unconsumed capsule is destroyed). readonly sets DLPack 1.0's read-only flag "
    "(versioned only)."),
  RBPY_METHODS_END,
};

}  // namespace

int add_dlpack_export(PyObject * module)
{
  return PyModule_AddFunctions(module, dlpack_functions);
}
