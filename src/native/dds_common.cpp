// Shared helpers of the rmw_fastrtps layer and its registration (see dds_common.hpp).
#include "dds_common.hpp"
#include "dds_writer.hpp"
#include "rmw_fastrtps_private.hpp"

#include <cstring>

#include "rcl/node.h"
#include "rcl/publisher.h"
#include "rcutils/error_handling.h"

namespace rbpy_dds
{

PyObject * DdsError = nullptr;
PyObject * UnsupportedRmwError = nullptr;

namespace
{

/// The rclpy handle of `arg` (an rclpy entity carries it in `.handle`), a new reference;
/// nullptr with TypeError when `arg` is neither. Plain ints are the caller's case.
PyObject * handle_of(PyObject * arg, const char * what)
{
  if (arg != nullptr && arg != Py_None && PyObject_HasAttrString(arg, "pointer")) {
    return Py_NewRef(arg);
  }
  if (arg != nullptr && arg != Py_None && PyObject_HasAttrString(arg, "handle")) {
    return PyObject_GetAttrString(arg, "handle");
  }
  PyErr_Format(
    PyExc_TypeError, "%s: expected a pointer int, an rclpy handle or an rclpy entity, got %.100s",
    what, arg ? Py_TYPE(arg)->tp_name : "NULL");
  return nullptr;
}

/// The pointer of a pointer int or of `handle.pointer`; nullptr with an exception.
void * pointer_of(PyObject * arg, bool is_handle, const char * what)
{
  PyObject * pointer = is_handle ? PyObject_GetAttrString(arg, "pointer") : Py_NewRef(arg);
  void * p = pointer ? PyLong_AsVoidPtr(pointer) : nullptr;
  Py_XDECREF(pointer);
  if (p == nullptr && !PyErr_Occurred()) {
    PyErr_Format(
      PyExc_ValueError, "%s: %s", what, is_handle ? "handle holds a null pointer" : "null pointer");
  }
  return p;
}

void exit_handle(PyObject * handle)
{
  PyObject * r = PyObject_CallMethod(handle, "__exit__", "OOO", Py_None, Py_None, Py_None);
  if (r == nullptr) {
    PyErr_WriteUnraisable(handle);
  }
  Py_XDECREF(r);
}

}  // namespace

int PinnedHandle::acquire(PyObject * arg, const char * what)
{
  release();
  if (arg != nullptr && PyLong_Check(arg)) {
    ptr_ = pointer_of(arg, false, what);
    return ptr_ ? 0 : -1;
  }
  PyObject * handle = handle_of(arg, what);
  if (handle == nullptr) {
    return -1;
  }
  // Enter first (raises if rclpy already destroyed it), then read the pointer.
  PyObject * entered = PyObject_CallMethod(handle, "__enter__", nullptr);
  void * p = entered ? pointer_of(handle, true, what) : nullptr;
  Py_XDECREF(entered);
  if (p == nullptr) {
    if (entered != nullptr) {
      rbpy_glue::SavedException error;
      exit_handle(handle);
    }
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
    return pointer_of(arg, false, what);
  }
  PyObject * handle = handle_of(arg, what);
  void * p = handle ? pointer_of(handle, true, what) : nullptr;
  Py_XDECREF(handle);
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
  rbpy_glue::SavedException error;
  exit_handle(handle);
  Py_DECREF(handle);
}

int check_handle_kind(PyObject * arg, const char * kind, const char * what)
{
  if (arg == nullptr || PyLong_Check(arg)) {
    return 0;  // a raw pointer: the caller vouches for its kind
  }
  PyObject * handle = handle_of(arg, what);
  if (handle == nullptr) {
    if (PyErr_ExceptionMatches(PyExc_TypeError)) {
      PyErr_Clear();  // PinnedHandle::acquire reports it
      return 0;
    }
    return -1;
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

PyObject * taken_tuple(PyObject * data, const rmw_message_info_t & info, PyObject * extra)
{
  PyObject * gid = data ? gid_bytes(info.publisher_gid.data) : nullptr;
  PyObject * info_dict = gid ? message_info_dict(info) : nullptr;
  PyObject * result = !info_dict ? nullptr : extra ?
    PyTuple_Pack(4, data, gid, info_dict, extra) : PyTuple_Pack(3, data, gid, info_dict);
  Py_XDECREF(data);
  Py_XDECREF(gid);
  Py_XDECREF(info_dict);
  return result;
}

int SerializedView::acquire(PyObject * data)
{
  if (PyObject_GetBuffer(data, &view_, PyBUF_C_CONTIGUOUS) < 0) {
    return -1;
  }
  held_ = true;
  if (view_.len < 4) {
    PyErr_SetString(
      PyExc_ValueError, "serialized message too short (needs the 4-byte CDR encapsulation)");
    return -1;
  }
  return 0;
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

rmw_publisher_t * pin_rmw_publisher(PyObject * arg, const char * what, PinnedHandle * pin)
{
  if (check_handle_kind(arg, "Publisher", what) < 0 || pin->acquire(arg, what) < 0) {
    return nullptr;
  }
  return fastrtps_handle(pin->get(), rcl_publisher_get_rmw_handle, "publisher");
}

rmw_node_t * pin_rmw_node(PyObject * arg, PinnedHandle * pin)
{
  if (pin->acquire(arg, "node") < 0) {
    return nullptr;
  }
  return fastrtps_handle(pin->get(), rcl_node_get_rmw_handle, "node");
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

PyMethodDef abi_functions[] = {
  RBPY_FUNCTION(set_private_layout_verified, METH_O,
    "set_private_layout_verified(verified: bool) -> None\n\n"
    "Allow (or forbid) the accesses to rmw_fastrtps's private layout; rosidl_buffer_py._dds\n"
    "allows them at import when the running libraries are the BUILT_AGAINST versions."),
  RBPY_FUNCTION(private_layout_verified, METH_NOARGS, "private_layout_verified() -> bool"),
  RBPY_METHODS_END,
};

/// BUILT_AGAINST: package -> version compiled against.
PyObject * built_against()
{
  PyObject * built = PyDict_New();
  for (const auto & entry : rbpy_dds::rmw_private::built_versions()) {
    PyObject * version = built ? PyUnicode_FromString(entry.version) : nullptr;
    if (version == nullptr || PyDict_SetItemString(built, entry.package, version) < 0) {
      Py_XDECREF(version);
      Py_XDECREF(built);
      return nullptr;
    }
    Py_DECREF(version);
  }
  return built;
}

/// A module exception `rosidl_buffer_py._native.<name>` (created once).
int add_exception(PyObject * module, PyObject ** exception, const char * name, const char * doc,
  PyObject * base)
{
  if (*exception == nullptr) {
    *exception = PyErr_NewExceptionWithDoc(
      (std::string("rosidl_buffer_py._native.") + name).c_str(), doc, base, nullptr);
  }
  return *exception ? PyModule_AddObjectRef(module, name, *exception) : -1;
}

}  // namespace

int add_dds_api(PyObject * module)
{
  using namespace rbpy_dds;
  if (add_exception(
      module, &DdsError, "DdsError", "A Fast DDS / rmw / rcl call of the native layer failed.",
      PyExc_RuntimeError) < 0 ||
    add_exception(
      module, &UnsupportedRmwError, "UnsupportedRmwError",
      "The entity does not belong to rmw_fastrtps_cpp; use plain rclpy instead.", DdsError) < 0 ||
    PyModule_AddStringConstant(module, "RMW_IMPLEMENTATION", kFastrtpsIdentifier) < 0 ||
    rbpy_glue::add_object(module, "BUILT_AGAINST", built_against()) < 0)
  {
    return -1;
  }
  for (PyMethodDef * table :
    {abi_functions, endpoint_functions, discovery_functions, channel_functions, codec_functions})
  {
    if (PyModule_AddFunctions(module, table) < 0) {
      return -1;
    }
  }
  return add_channel_types(module);
}
