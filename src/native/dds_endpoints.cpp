// Per-endpoint helpers on rclpy publishers/subscriptions: GID, USER_DATA, take with GID.
//
//   endpoint_gid(endpoint, kind) -> bytes
//   get_user_data(endpoint, kind) -> bytes
//   set_user_data(endpoint, kind, data) -> None
//   take_serialized_with_gid(subscription) -> (bytes, publisher_gid, info) | None
//
// `endpoint` is an rcl_publisher_t* / rcl_subscription_t* (int), an rclpy handle, or an
// rclpy Publisher/Subscription; `kind` is "publisher" or "subscription" and must match it.
#include <vector>

#include "dds_common.hpp"

#include "fastdds/dds/publisher/DataWriter.hpp"
#include "fastdds/dds/publisher/qos/DataWriterQos.hpp"
#include "fastdds/dds/subscriber/DataReader.hpp"
#include "fastdds/dds/subscriber/qos/DataReaderQos.hpp"
#include "rcl/error_handling.h"
#include "rcl/publisher.h"
#include "rcl/subscription.h"
#include "rmw/serialized_message.h"
#include "rmw_fastrtps_cpp/get_publisher.hpp"
#include "rmw_fastrtps_cpp/get_subscriber.hpp"
#include "rmw_fastrtps_shared_cpp/guid_utils.hpp"

namespace rbpy_dds
{
namespace
{

using eprosima::fastdds::dds::DataReader;
using eprosima::fastdds::dds::DataWriter;
using eprosima::fastrtps::types::ReturnCode_t;

/// The DataWriter or DataReader behind an rcl endpoint (GIL released inside).
struct DdsEndpoint
{
  DataWriter * writer = nullptr;
  DataReader * reader = nullptr;
};

int resolve_endpoint(void * rcl_endpoint, bool is_publisher, DdsEndpoint * out)
{
  const char * identifier = nullptr;
  bool invalid = false;
  {
    GilRelease nogil;
    if (is_publisher) {
      rmw_publisher_t * pub =
        rcl_publisher_get_rmw_handle(static_cast<const rcl_publisher_t *>(rcl_endpoint));
      if (pub == nullptr) {
        invalid = true;
      } else {
        identifier = pub->implementation_identifier;
        out->writer = rmw_fastrtps_cpp::get_datawriter(pub);
      }
    } else {
      rmw_subscription_t * sub =
        rcl_subscription_get_rmw_handle(static_cast<const rcl_subscription_t *>(rcl_endpoint));
      if (sub == nullptr) {
        invalid = true;
      } else {
        identifier = sub->implementation_identifier;
        out->reader = rmw_fastrtps_cpp::get_datareader(sub);
      }
    }
    if (invalid) {
      rcl_reset_error();
    }
  }
  const char * what = is_publisher ? "publisher" : "subscription";
  if (invalid) {
    PyErr_Format(DdsError, "the rcl %s is not valid (already destroyed?)", what);
    return -1;
  }
  if (check_identifier(identifier, what) < 0) {
    return -1;
  }
  if (out->writer == nullptr && out->reader == nullptr) {
    PyErr_Format(
      DdsError, "rmw_fastrtps_cpp returned no DDS entity for this %s (a second copy of "
      "librmw_fastrtps_cpp loaded?)", what);
    return -1;
  }
  return 0;
}

PyObject * endpoint_gid(PyObject *, PyObject * args)
{
  PyObject * endpoint_arg;
  const char * kind;
  if (!PyArg_ParseTuple(args, "Os:endpoint_gid", &endpoint_arg, &kind)) {
    return nullptr;
  }
  bool is_publisher;
  if (parse_kind(kind, &is_publisher) < 0) {
    return nullptr;
  }
  PinnedHandle endpoint;
  if (endpoint.acquire(endpoint_arg, "endpoint") < 0) {
    return nullptr;
  }
  DdsEndpoint dds;
  if (resolve_endpoint(endpoint.get(), is_publisher, &dds) < 0) {
    return nullptr;
  }
  uint8_t gid[RMW_GID_STORAGE_SIZE] = {};
  {
    GilRelease nogil;
    const auto & guid = dds.writer ? dds.writer->guid() : dds.reader->guid();
    rmw_fastrtps_shared_cpp::copy_from_fastrtps_guid_to_byte_array(guid, gid);
  }
  return gid_bytes(gid);
}

PyObject * get_user_data(PyObject *, PyObject * args)
{
  PyObject * endpoint_arg;
  const char * kind;
  if (!PyArg_ParseTuple(args, "Os:get_user_data", &endpoint_arg, &kind)) {
    return nullptr;
  }
  bool is_publisher;
  if (parse_kind(kind, &is_publisher) < 0) {
    return nullptr;
  }
  PinnedHandle endpoint;
  if (endpoint.acquire(endpoint_arg, "endpoint") < 0) {
    return nullptr;
  }
  DdsEndpoint dds;
  if (resolve_endpoint(endpoint.get(), is_publisher, &dds) < 0) {
    return nullptr;
  }
  std::vector<uint8_t> data;
  {
    GilRelease nogil;
    if (dds.writer) {
      data = dds.writer->get_qos().user_data().data_vec();
    } else {
      data = dds.reader->get_qos().user_data().data_vec();
    }
  }
  return PyBytes_FromStringAndSize(
    reinterpret_cast<const char *>(data.data()), static_cast<Py_ssize_t>(data.size()));
}

PyObject * set_user_data(PyObject *, PyObject * args)
{
  PyObject * endpoint_arg;
  const char * kind;
  Py_buffer view;
  if (!PyArg_ParseTuple(args, "Osy*:set_user_data", &endpoint_arg, &kind, &view)) {
    return nullptr;
  }
  std::vector<uint8_t> data(
    static_cast<const uint8_t *>(view.buf), static_cast<const uint8_t *>(view.buf) + view.len);
  PyBuffer_Release(&view);
  bool is_publisher;
  if (parse_kind(kind, &is_publisher) < 0) {
    return nullptr;
  }
  // USER_DATA travels in a parameter whose length is a uint16; keep well below it.
  if (data.size() > 32768) {
    PyErr_Format(PyExc_ValueError, "user_data too long (%zu bytes, at most 32768)", data.size());
    return nullptr;
  }
  PinnedHandle endpoint;
  if (endpoint.acquire(endpoint_arg, "endpoint") < 0) {
    return nullptr;
  }
  DdsEndpoint dds;
  if (resolve_endpoint(endpoint.get(), is_publisher, &dds) < 0) {
    return nullptr;
  }
  ReturnCode_t rc;
  bool stored = false;
  {
    GilRelease nogil;
    // No lock of ours is held: set_qos() may run discovery callbacks synchronously.
    if (dds.writer) {
      auto qos = dds.writer->get_qos();
      qos.user_data().data_vec(data);
      rc = dds.writer->set_qos(qos);
      stored = dds.writer->get_qos().user_data().data_vec() == data;
    } else {
      auto qos = dds.reader->get_qos();
      qos.user_data().data_vec(data);
      rc = dds.reader->set_qos(qos);
      stored = dds.reader->get_qos().user_data().data_vec() == data;
    }
  }
  if (rc != ReturnCode_t::RETCODE_OK) {
    PyErr_Format(
      DdsError, "Fast DDS refused the new USER_DATA QoS (return code %d)",
      static_cast<int>(rc()));
    return nullptr;
  }
  if (!stored) {
    PyErr_SetString(DdsError, "Fast DDS truncated the USER_DATA (participant max_user_data?)");
    return nullptr;
  }
  Py_RETURN_NONE;
}

PyObject * take_serialized_with_gid(PyObject *, PyObject * args)
{
  PyObject * sub_arg;
  if (!PyArg_ParseTuple(args, "O:take_serialized_with_gid", &sub_arg)) {
    return nullptr;
  }
  PinnedHandle sub;
  if (sub.acquire(sub_arg, "subscription") < 0) {
    return nullptr;
  }
  rcl_serialized_message_t msg = rmw_get_zero_initialized_serialized_message();
  rmw_message_info_t info = rmw_get_zero_initialized_message_info();
  rcl_ret_t ret;
  std::string error;
  {
    GilRelease nogil;
    rcutils_allocator_t allocator = rcutils_get_default_allocator();
    ret = rmw_serialized_message_init(&msg, 0, &allocator);
    if (ret == RCL_RET_OK) {
      ret = rcl_take_serialized_message(
        static_cast<const rcl_subscription_t *>(sub.get()), &msg, &info, nullptr);
    }
    if (ret != RCL_RET_OK && ret != RCL_RET_SUBSCRIPTION_TAKE_FAILED) {
      error = take_rmw_error();
    }
  }
  PyObject * result = nullptr;
  if (ret == RCL_RET_SUBSCRIPTION_TAKE_FAILED) {
    Py_INCREF(Py_None);
    result = Py_None;
  } else if (ret != RCL_RET_OK) {
    raise_rmw_error("rcl_take_serialized_message failed", error);
  } else {
    PyObject * data = PyBytes_FromStringAndSize(
      reinterpret_cast<const char *>(msg.buffer), static_cast<Py_ssize_t>(msg.buffer_length));
    PyObject * gid = data ? gid_bytes(info.publisher_gid.data) : nullptr;
    PyObject * info_dict = gid ? message_info_dict(info) : nullptr;
    if (info_dict) {
      result = PyTuple_Pack(3, data, gid, info_dict);
    }
    Py_XDECREF(data);
    Py_XDECREF(gid);
    Py_XDECREF(info_dict);
  }
  if (msg.buffer != nullptr) {
    GilRelease nogil;
    if (rmw_serialized_message_fini(&msg) != RMW_RET_OK) {
      rcutils_reset_error();
    }
  }
  return result;
}

PyMethodDef endpoint_methods[] = {
  {"endpoint_gid", endpoint_gid, METH_VARARGS,
    "endpoint_gid(endpoint, kind) -> bytes\n\n"
    "The 16-byte GID of an rcl publisher/subscription (kind 'publisher'/'subscription'), as\n"
    "Node.get_publishers_info_by_topic() reports it in endpoint_gid."},
  {"get_user_data", get_user_data, METH_VARARGS,
    "get_user_data(endpoint, kind) -> bytes\n\n"
    "The USER_DATA QoS of the DataWriter/DataReader behind an rcl publisher/subscription."},
  {"set_user_data", set_user_data, METH_VARARGS,
    "set_user_data(endpoint, kind, data: bytes) -> None\n\n"
    "Replace that USER_DATA (keep rmw's 'typehash=...;' prefix!). Remote participants see\n"
    "the change as a 'changed' discovery event."},
  {"take_serialized_with_gid", take_serialized_with_gid, METH_VARARGS,
    "take_serialized_with_gid(subscription) -> (bytes, publisher_gid, info) | None\n\n"
    "rcl_take_serialized_message on an rcl subscription: the CDR bytes, the 16-byte GID of\n"
    "the publisher and an rclpy-like message info dict; None when nothing is there."},
  {nullptr, nullptr, 0, nullptr},
};

}  // namespace

int add_dds_endpoint_functions(PyObject * module)
{
  return PyModule_AddFunctions(module, endpoint_methods);
}

}  // namespace rbpy_dds
