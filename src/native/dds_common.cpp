// Shared helpers of the rmw_fastrtps layer and its registration (see dds_common.hpp).
#include "dds_common.hpp"
#include "dds_writer.hpp"
#include "rmw_fastrtps_private.hpp"

#include <cstring>

#include "rcutils/error_handling.h"

namespace rbpy_dds
{

PyObject * DdsError = nullptr;
PyObject * UnsupportedRmwError = nullptr;

int PinnedHandle::acquire(PyObject * arg, const char * what)
{
  release();
  if (arg == nullptr || arg == Py_None) {
    PyErr_Format(PyExc_TypeError, "%s: expected a pointer int or an rclpy handle, got None", what);
    return -1;
  }
  if (PyLong_Check(arg)) {
    void * p = PyLong_AsVoidPtr(arg);
    if (p == nullptr) {
      if (!PyErr_Occurred()) {
        PyErr_Format(PyExc_ValueError, "%s: null pointer", what);
      }
      return -1;
    }
    ptr_ = p;
    return 0;
  }
  // An rclpy entity (Node, Publisher, ...) carries its handle in `.handle`.
  PyObject * handle = nullptr;
  if (PyObject_HasAttrString(arg, "pointer")) {
    handle = arg;
    Py_INCREF(handle);
  } else if (PyObject_HasAttrString(arg, "handle")) {
    handle = PyObject_GetAttrString(arg, "handle");
    if (handle == nullptr) {
      return -1;
    }
  } else {
    PyErr_Format(
      PyExc_TypeError, "%s: expected a pointer int, an rclpy handle or an rclpy entity, got %.100s",
      what, Py_TYPE(arg)->tp_name);
    return -1;
  }
  // Enter first (raises if rclpy already destroyed it), then read the pointer.
  PyObject * entered = PyObject_CallMethod(handle, "__enter__", nullptr);
  if (entered == nullptr) {
    Py_DECREF(handle);
    return -1;
  }
  Py_DECREF(entered);
  PyObject * pointer = PyObject_GetAttrString(handle, "pointer");
  void * p = pointer ? PyLong_AsVoidPtr(pointer) : nullptr;
  Py_XDECREF(pointer);
  if (p == nullptr) {
    if (!PyErr_Occurred()) {
      PyErr_Format(PyExc_ValueError, "%s: handle holds a null pointer", what);
    }
    PyObject * r = PyObject_CallMethod(handle, "__exit__", "OOO", Py_None, Py_None, Py_None);
    Py_XDECREF(r);
    Py_DECREF(handle);
    return -1;
  }
  handle_ = handle;
  ptr_ = p;
  return 0;
}

void * PinnedHandle::peek(PyObject * arg, const char * what)
{
  if (arg != nullptr && PyLong_Check(arg)) {
    void * p = PyLong_AsVoidPtr(arg);
    if (p == nullptr && !PyErr_Occurred()) {
      PyErr_Format(PyExc_ValueError, "%s: null pointer", what);
    }
    return p;
  }
  PyObject * handle = nullptr;
  if (arg != nullptr && arg != Py_None && PyObject_HasAttrString(arg, "pointer")) {
    handle = arg;
    Py_INCREF(handle);
  } else if (arg != nullptr && arg != Py_None && PyObject_HasAttrString(arg, "handle")) {
    handle = PyObject_GetAttrString(arg, "handle");
    if (handle == nullptr) {
      return nullptr;
    }
  } else {
    PyErr_Format(
      PyExc_TypeError, "%s: expected a pointer int, an rclpy handle or an rclpy entity, got %.100s",
      what, arg ? Py_TYPE(arg)->tp_name : "NULL");
    return nullptr;
  }
  PyObject * pointer = PyObject_GetAttrString(handle, "pointer");
  Py_DECREF(handle);
  void * p = pointer ? PyLong_AsVoidPtr(pointer) : nullptr;
  Py_XDECREF(pointer);
  if (p == nullptr && !PyErr_Occurred()) {
    PyErr_Format(PyExc_ValueError, "%s: handle holds a null pointer", what);
  }
  return p;
}

void PinnedHandle::release()
{
  ptr_ = nullptr;
  PyObject * handle = handle_;
  if (handle == nullptr) {
    return;
  }
  handle_ = nullptr;
  PyObject * exc_type, * exc_value, * exc_tb;
  PyErr_Fetch(&exc_type, &exc_value, &exc_tb);
  PyObject * r = PyObject_CallMethod(handle, "__exit__", "OOO", Py_None, Py_None, Py_None);
  if (r == nullptr) {
    PyErr_WriteUnraisable(handle);
  }
  Py_XDECREF(r);
  Py_DECREF(handle);
  PyErr_Restore(exc_type, exc_value, exc_tb);
}

int check_handle_kind(PyObject * arg, const char * kind, const char * what)
{
  if (arg == nullptr || PyLong_Check(arg)) {
    return 0;  // a raw pointer: the caller vouches for its kind
  }
  PyObject * handle = nullptr;
  if (PyObject_HasAttrString(arg, "pointer")) {
    handle = arg;
    Py_INCREF(handle);
  } else if (PyObject_HasAttrString(arg, "handle")) {
    handle = PyObject_GetAttrString(arg, "handle");
    if (handle == nullptr) {
      return -1;
    }
  } else {
    return 0;  // PinnedHandle::acquire reports it
  }
  const char * name = Py_TYPE(handle)->tp_name;
  const char * dot = std::strrchr(name, '.');
  const char * base = dot ? dot + 1 : name;
  const bool ok = std::strcmp(base, kind) == 0;
  if (!ok) {
    PyErr_Format(
      PyExc_TypeError, "%s: expected an rclpy %s (or its handle), got %.100s", what, kind,
      Py_TYPE(arg)->tp_name);
  }
  Py_DECREF(handle);
  return ok ? 0 : -1;
}

std::string take_rmw_error()
{
  if (!rcutils_error_is_set()) {
    return "unknown error";
  }
  std::string s = rcutils_get_error_string().str;
  rcutils_reset_error();
  return s;
}

PyObject * raise_rmw_error(const std::string & what, const std::string & rmw_error)
{
  PyErr_Format(DdsError, "%s: %s", what.c_str(), rmw_error.c_str());
  return nullptr;
}

PyObject * gid_bytes(const uint8_t * data)
{
  return PyBytes_FromStringAndSize(reinterpret_cast<const char *>(data), RMW_GID_STORAGE_SIZE);
}

PyObject * gid_list(const std::vector<GidArray> & gids)
{
  PyObject * list = PyList_New(static_cast<Py_ssize_t>(gids.size()));
  if (list == nullptr) {
    return nullptr;
  }
  for (size_t i = 0; i < gids.size(); ++i) {
    PyObject * gid = gid_bytes(gids[i].data());
    if (gid == nullptr) {
      Py_DECREF(list);
      return nullptr;
    }
    PyList_SET_ITEM(list, static_cast<Py_ssize_t>(i), gid);
  }
  return list;
}

int parse_source_timestamp(PyObject * arg, int64_t * out)
{
  if (arg == nullptr || !PyLong_Check(arg) || PyBool_Check(arg)) {
    PyErr_Format(
      PyExc_TypeError, "source_timestamp must be an int (ns since the epoch), got %.100s",
      arg ? Py_TYPE(arg)->tp_name : "NULL");
    return -1;
  }
  int overflow = 0;
  const long long value = PyLong_AsLongLongAndOverflow(arg, &overflow);
  if (value == -1 && PyErr_Occurred()) {
    return -1;
  }
  if (overflow != 0 || value < 0 || value > kMaxSourceTimestampNs) {
    PyErr_Format(
      PyExc_ValueError, "source_timestamp out of range (0 <= ns <= %lld, Fast DDS Time_t)",
      static_cast<long long>(kMaxSourceTimestampNs));
    return -1;
  }
  *out = static_cast<int64_t>(value);
  return 0;
}

PyObject * message_info_dict(const rmw_message_info_t & info)
{
  return Py_BuildValue(
    "{s:L,s:L,s:K,s:K,s:O}",
    "source_timestamp", static_cast<long long>(info.source_timestamp),
    "received_timestamp", static_cast<long long>(info.received_timestamp),
    "publication_sequence_number",
    static_cast<unsigned long long>(info.publication_sequence_number),
    "reception_sequence_number",
    static_cast<unsigned long long>(info.reception_sequence_number),
    "from_intra_process", info.from_intra_process ? Py_True : Py_False);
}

int parse_kind(const char * kind, bool * is_publisher)
{
  if (std::strcmp(kind, "publisher") == 0 || std::strcmp(kind, "writer") == 0) {
    *is_publisher = true;
    return 0;
  }
  if (std::strcmp(kind, "subscription") == 0 || std::strcmp(kind, "reader") == 0) {
    *is_publisher = false;
    return 0;
  }
  PyErr_Format(
    PyExc_ValueError, "kind must be 'publisher' or 'subscription', got '%s'", kind);
  return -1;
}

int check_identifier(const char * identifier, const char * what)
{
  if (identifier == nullptr || std::strcmp(identifier, kFastrtpsIdentifier) != 0) {
    PyErr_Format(
      UnsupportedRmwError, "%s belongs to rmw implementation '%s'; only '%s' is supported",
      what, identifier ? identifier : "(none)", kFastrtpsIdentifier);
    return -1;
  }
  return 0;
}

}  // namespace rbpy_dds

namespace
{

PyObject * set_private_layout_verified(PyObject *, PyObject * arg)
{
  const int verified = PyObject_IsTrue(arg);
  if (verified < 0) {
    return nullptr;
  }
  rbpy_dds::rmw_private::set_layout_verified(verified != 0);
  Py_RETURN_NONE;
}

PyObject * private_layout_verified(PyObject *, PyObject *)
{
  return PyBool_FromLong(rbpy_dds::rmw_private::layout_verified());
}

PyMethodDef abi_methods[] = {
  {"set_private_layout_verified", set_private_layout_verified, METH_O,
    "set_private_layout_verified(verified: bool) -> None\n\n"
    "Allow (or forbid) the accesses to rmw_fastrtps's private layout; rosidl_buffer_py._dds\n"
    "allows them at import when the running libraries are the BUILT_AGAINST versions."},
  {"private_layout_verified", private_layout_verified, METH_NOARGS,
    "private_layout_verified() -> bool"},
  {nullptr, nullptr, 0, nullptr},
};

int add_abi_api(PyObject * module)
{
  PyObject * built = PyDict_New();
  if (built == nullptr) {
    return -1;
  }
  for (const auto & entry : rbpy_dds::rmw_private::built_versions()) {
    PyObject * version = PyUnicode_FromString(entry.version);
    if (version == nullptr || PyDict_SetItemString(built, entry.package, version) < 0) {
      Py_XDECREF(version);
      Py_DECREF(built);
      return -1;
    }
    Py_DECREF(version);
  }
  if (PyModule_AddObject(module, "BUILT_AGAINST", built) < 0) {
    Py_DECREF(built);
    return -1;
  }
  return PyModule_AddFunctions(module, abi_methods);
}

}  // namespace

int add_dds_api(PyObject * module)
{
  using rbpy_dds::DdsError;
  using rbpy_dds::UnsupportedRmwError;
  if (DdsError == nullptr) {
    DdsError = PyErr_NewExceptionWithDoc(
      "rosidl_buffer_py._native.DdsError",
      "A Fast DDS / rmw / rcl call of the native layer failed.", PyExc_RuntimeError, nullptr);
    if (DdsError == nullptr) {
      return -1;
    }
  }
  if (UnsupportedRmwError == nullptr) {
    UnsupportedRmwError = PyErr_NewExceptionWithDoc(
      "rosidl_buffer_py._native.UnsupportedRmwError",
      "The entity does not belong to rmw_fastrtps_cpp; use plain rclpy instead.",
      DdsError, nullptr);
    if (UnsupportedRmwError == nullptr) {
      return -1;
    }
  }
  Py_INCREF(DdsError);
  if (PyModule_AddObject(module, "DdsError", DdsError) < 0) {
    Py_DECREF(DdsError);
    return -1;
  }
  Py_INCREF(UnsupportedRmwError);
  if (PyModule_AddObject(module, "UnsupportedRmwError", UnsupportedRmwError) < 0) {
    Py_DECREF(UnsupportedRmwError);
    return -1;
  }
  if (PyModule_AddStringConstant(module, "RMW_IMPLEMENTATION", rbpy_dds::kFastrtpsIdentifier) < 0) {
    return -1;
  }
  if (add_abi_api(module) < 0 ||
    rbpy_dds::add_dds_endpoint_functions(module) < 0 ||
    rbpy_dds::add_dds_discovery_functions(module) < 0 ||
    rbpy_dds::add_dds_channel_types(module) < 0 ||
    rbpy_dds::add_codec_functions(module) < 0)
  {
    return -1;
  }
  return 0;
}
