// BufferBase: the one piece of rosidl_buffer_py.Buffer that Python 3.11 cannot express.
//
// A pure-Python class cannot export the buffer protocol before Python 3.12 (PEP 688), yet
// `memoryview(buf)` and `numpy.asarray(buf)` must work without a copy. BufferBase holds an
// "exporter" (any object that supports the buffer protocol, typically a memoryview over an
// mmap) and re-exports it with itself as the owner, so that every view keeps the Buffer, and
// with it the backend's hold on the memory, alive.
#include "buffer_base.hpp"

#include <structmember.h>

#include "py_glue.hpp"

namespace
{

struct BufferBaseObject
{
  PyObject_HEAD
  PyObject * exporter;  // owned; NULL when the memory is not host-addressable
  PyObject * weakrefs;
};

int buffer_base_init(PyObject * self, PyObject * args, PyObject * kwds)
{
  static const char * kwlist[] = {"exporter", nullptr};
  PyObject * exporter = Py_None;
  if (!PyArg_ParseTupleAndKeywords(
      args, kwds, "|O:BufferBase", const_cast<char **>(kwlist), &exporter))
  {
    return -1;
  }
  auto * obj = reinterpret_cast<BufferBaseObject *>(self);
  if (obj->exporter != nullptr) {
    PyErr_SetString(PyExc_RuntimeError, "BufferBase is already bound to its memory");
    return -1;
  }
  if (exporter != Py_None) {
    if (!PyObject_CheckBuffer(exporter)) {
      PyErr_Format(
        PyExc_TypeError, "exporter must support the buffer protocol or be None, got %.100s",
        Py_TYPE(exporter)->tp_name);
      return -1;
    }
    Py_INCREF(exporter);
    obj->exporter = exporter;
  }
  return 0;
}

int buffer_base_getbuffer(PyObject * self, Py_buffer * view, int flags)
{
  auto * obj = reinterpret_cast<BufferBaseObject *>(self);
  if (obj->exporter == nullptr) {
    PyErr_Format(
      PyExc_BufferError, "%.100s has no host-addressable memory", Py_TYPE(self)->tp_name);
    view->obj = nullptr;
    return -1;
  }
  auto * inner = static_cast<Py_buffer *>(PyMem_Malloc(sizeof(Py_buffer)));
  if (inner == nullptr) {
    PyErr_NoMemory();
    view->obj = nullptr;
    return -1;
  }
  if (PyObject_GetBuffer(obj->exporter, inner, flags) < 0) {
    PyMem_Free(inner);
    view->obj = nullptr;
    return -1;
  }
  *view = *inner;  // shape/strides/format point into `inner`, which lives until release
  Py_INCREF(self);
  view->obj = self;
  view->internal = inner;
  return 0;
}

void buffer_base_releasebuffer(PyObject *, Py_buffer * view)
{
  auto * inner = static_cast<Py_buffer *>(view->internal);
  if (inner != nullptr) {
    PyBuffer_Release(inner);
    PyMem_Free(inner);
    view->internal = nullptr;
  }
}

int buffer_base_traverse(PyObject * self, visitproc visit, void * arg)
{
  Py_VISIT(reinterpret_cast<BufferBaseObject *>(self)->exporter);
  Py_VISIT(Py_TYPE(self));
  return 0;
}

int buffer_base_clear(PyObject * self)
{
  Py_CLEAR(reinterpret_cast<BufferBaseObject *>(self)->exporter);
  return 0;
}

void buffer_base_dealloc(PyObject * self)
{
  PyTypeObject * tp = Py_TYPE(self);
  PyObject_GC_UnTrack(self);
  if (reinterpret_cast<BufferBaseObject *>(self)->weakrefs != nullptr) {
    PyObject_ClearWeakRefs(self);
  }
  buffer_base_clear(self);
  tp->tp_free(self);
  Py_DECREF(tp);
}

PyObject * buffer_base_has_host_memory(PyObject * self, void *)
{
  return PyBool_FromLong(reinterpret_cast<BufferBaseObject *>(self)->exporter != nullptr);
}

PyGetSetDef buffer_base_getset[] = {
  {"_has_host_memory", buffer_base_has_host_memory, nullptr,
    "True when the memory can be exported through the buffer protocol.", nullptr},
  {nullptr, nullptr, nullptr, nullptr, nullptr},
};

PyMemberDef buffer_base_members[] = {
  {"__weaklistoffset__", T_PYSSIZET, offsetof(BufferBaseObject, weakrefs), READONLY, nullptr},
  {nullptr, 0, 0, 0, nullptr},
};

PyType_Slot buffer_base_slots[] = {
  {Py_tp_doc, const_cast<char *>(
      "BufferBase(exporter=None)\n--\n\n"
      "Re-exports `exporter`'s buffer with this object as the owner. Base of "
      "rosidl_buffer_py.Buffer; not meant to be used directly.")},
  {Py_tp_init, reinterpret_cast<void *>(buffer_base_init)},
  {Py_tp_new, reinterpret_cast<void *>(PyType_GenericNew)},
  {Py_tp_dealloc, reinterpret_cast<void *>(buffer_base_dealloc)},
  {Py_tp_traverse, reinterpret_cast<void *>(buffer_base_traverse)},
  {Py_tp_clear, reinterpret_cast<void *>(buffer_base_clear)},
  {Py_tp_getset, buffer_base_getset},
  {Py_tp_members, buffer_base_members},
  {Py_bf_getbuffer, reinterpret_cast<void *>(buffer_base_getbuffer)},
  {Py_bf_releasebuffer, reinterpret_cast<void *>(buffer_base_releasebuffer)},
  {0, nullptr},
};

PyType_Spec buffer_base_spec = {
  "rosidl_buffer_py._native.BufferBase",
  sizeof(BufferBaseObject),
  0,
  Py_TPFLAGS_DEFAULT | Py_TPFLAGS_BASETYPE | Py_TPFLAGS_HAVE_GC,
  buffer_base_slots,
};

}  // namespace

int add_buffer_base_type(PyObject * module)
{
  return rbpy_glue::add_type(module, &buffer_base_spec) ? 0 : -1;
}
