// ROS messages on the C side (see MessageSupport in dds_common.hpp): the conversions rclpy's
// own publish and take do, so that CPU data crosses channels without Python-level CDR work.
#include "dds_common.hpp"

#include <exception>

#include "fastcdr/Cdr.h"
#include "fastcdr/FastBuffer.h"
#include "rcutils/error_handling.h"
#include "rmw/rmw.h"
#include "rosidl_runtime_c/message_type_support_struct.h"

namespace rbpy_dds
{
namespace
{

void * capsule_pointer(PyObject * msg_class, const char * attribute)
{
  PyObject * capsule = PyObject_GetAttrString(msg_class, attribute);
  if (capsule == nullptr) {
    return nullptr;
  }
  void * pointer = nullptr;
  if (PyCapsule_CheckExact(capsule)) {
    pointer = PyCapsule_GetPointer(capsule, PyCapsule_GetName(capsule));
  } else {
    PyErr_Format(PyExc_TypeError, "%s is not a capsule", attribute);
  }
  Py_DECREF(capsule);
  return pointer;
}

}  // namespace

int MessageSupport::load(PyObject * msg_class)
{
  PyObject * present = PyObject_GetAttrString(msg_class, "_CONVERT_TO_PY");
  const bool imported = present != nullptr && present != Py_None;
  Py_XDECREF(present);
  PyErr_Clear();
  if (!imported) {
    // Generated metaclasses hold None until __import_type_support__(), as rclpy's create_* do.
    PyObject * meta = PyObject_GetAttrString(msg_class, "__class__");
    PyObject * r = meta ? PyObject_CallMethod(meta, "__import_type_support__", nullptr) : nullptr;
    Py_XDECREF(meta);
    if (r == nullptr) {
      PyErr_Clear();
    }
    Py_XDECREF(r);
  }
  type_support = static_cast<const rosidl_message_type_support_t *>(
    capsule_pointer(msg_class, "_TYPE_SUPPORT"));
  create = reinterpret_cast<void * (*)()>(capsule_pointer(msg_class, "_CREATE_ROS_MESSAGE"));
  destroy = reinterpret_cast<void (*)(void *)>(
    capsule_pointer(msg_class, "_DESTROY_ROS_MESSAGE"));
  from_py = reinterpret_cast<bool (*)(PyObject *, void *)>(
    capsule_pointer(msg_class, "_CONVERT_FROM_PY"));
  to_py = reinterpret_cast<PyObject * (*)(void *)>(capsule_pointer(msg_class, "_CONVERT_TO_PY"));
  if (!type_support || !create || !destroy || !from_py || !to_py) {
    PyErr_Clear();
    PyErr_Format(
      PyExc_TypeError, "%.200R is not a generated ROS message class with type support",
      msg_class);
    return -1;
  }
  const rosidl_message_type_support_t * handle =
    get_message_typesupport_handle(type_support, "rosidl_typesupport_fastrtps_c");
  if (handle == nullptr) {
    rcutils_reset_error();
    PyErr_Format(
      PyExc_TypeError, "%.200R has no rosidl_typesupport_fastrtps_c type support", msg_class);
    return -1;
  }
  callbacks = static_cast<const message_type_support_callbacks_t *>(handle->data);
  return 0;
}

bool try_deserialize(
  const MessageSupport & support, const rmw_serialized_message_t & serialized,
  OwnedRosMessage * ros_message)
{
  // Only XCDR1 (what ROS 2 writes): other encapsulations go to the codec, which names them.
  const uint8_t * cdr = serialized.buffer;
  if (serialized.buffer_length < 4 || cdr[0] != 0 || cdr[1] > 1) {
    return false;
  }
  void * msg = ros_message->create();
  if (msg == nullptr) {
    return false;
  }
  // What rmw_deserialize does, minus the rmw TypeSupport object it builds (and frees) on every
  // call: the generated callbacks read the CDR straight into the C message.
  eprosima::fastcdr::FastBuffer buffer(
    reinterpret_cast<char *>(serialized.buffer), serialized.buffer_length);
  eprosima::fastcdr::Cdr deser(
    buffer, eprosima::fastcdr::Cdr::DEFAULT_ENDIAN, eprosima::fastcdr::CdrVersion::XCDRv1);
  try {
    deser.read_encapsulation();
    return support.callbacks->cdr_deserialize(deser, msg);
  } catch (const std::exception &) {  // fastcdr's NotEnoughMemoryException, bad_alloc, ...
    return false;
  }
}

PyObject * serialized_bytes(const rmw_serialized_message_t & serialized)
{
  return PyBytes_FromStringAndSize(
    reinterpret_cast<const char *>(serialized.buffer),
    static_cast<Py_ssize_t>(serialized.buffer_length));
}

}  // namespace rbpy_dds
