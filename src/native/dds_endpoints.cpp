// Per-endpoint helpers on rclpy publishers/subscriptions: GID, USER_DATA, take with GID.
//
//   endpoint_gid(endpoint, kind) -> bytes
//   get_user_data(endpoint, kind) -> bytes
//   set_user_data(endpoint, kind, data) -> None
//   hold_enabling(node, kind, hold) -> None
//   take_serialized_with_gid(subscription) -> (bytes, publisher_gid, info) | None
//   take_message_with_gid(subscription, msg_class, max_size=-1, program=None)
//       -> (message | bytes, gid, info) | None
//   publish_serialized(publisher, data, source_timestamp) -> None
//   matched_subscription_gids(publisher) -> list[bytes]
//   exclude_from_next_write(publisher, reader_gids) -> bool
//   remove_write_exclusions(publisher) -> None
//   set_new_message_wakeup(subscription, guard_condition) -> None
//   clear_new_message_wakeup(subscription) -> None
//
// `endpoint` is an rcl_publisher_t* / rcl_subscription_t* (int), an rclpy handle, or an
// rclpy Publisher/Subscription; `kind` is "publisher" or "subscription" and must match it.
#include <algorithm>
#include <cstring>
#include <map>
#include <mutex>
#include <vector>

#include "dds_common.hpp"
#include "dds_writer.hpp"
#include "rmw_fastrtps_private.hpp"

#include "fastdds/dds/publisher/DataWriter.hpp"
#include "fastdds/dds/publisher/qos/DataWriterQos.hpp"
#include "fastdds/dds/subscriber/DataReader.hpp"
#include "fastdds/dds/subscriber/SampleInfo.hpp"
#include "fastcdr/Cdr.h"
#include "rmw_fastrtps_shared_cpp/TypeSupport.hpp"
#include "fastdds/dds/subscriber/qos/DataReaderQos.hpp"
#include "rcl/error_handling.h"
#include "rcl/guard_condition.h"
#include "rcl/node.h"
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
  const char * what = is_publisher ? "publisher" : "subscription";
  if (is_publisher) {
    rmw_publisher_t * pub = fastrtps_handle(rcl_endpoint, rcl_publisher_get_rmw_handle, what);
    if (pub == nullptr) {
      return -1;
    }
    out->writer = rmw_fastrtps_cpp::get_datawriter(pub);
  } else {
    rmw_subscription_t * sub =
      fastrtps_handle(rcl_endpoint, rcl_subscription_get_rmw_handle, what);
    if (sub == nullptr) {
      return -1;
    }
    out->reader = rmw_fastrtps_cpp::get_datareader(sub);
  }
  if (out->writer == nullptr && out->reader == nullptr) {
    PyErr_Format(
      DdsError, "rmw_fastrtps_cpp returned no DDS entity for this %s (a second copy of "
      "librmw_fastrtps_cpp loaded?)", what);
    return -1;
  }
  return 0;
}

/// Parse `kind`, pin the rclpy endpoint handle and find its DataWriter/DataReader.
/// Returns 0, or -1 with an exception set; `pin` keeps the handle alive for the caller.
int open_endpoint(
  PyObject * endpoint_arg, const char * kind, PinnedHandle * pin, DdsEndpoint * dds)
{
  bool is_publisher;
  if (parse_kind(kind, &is_publisher) < 0 || pin->acquire(endpoint_arg, "endpoint") < 0) {
    return -1;
  }
  return resolve_endpoint(pin->get(), is_publisher, dds);
}

/// `f(entity)` on the endpoint's DataWriter or DataReader, GIL released.
template<typename F>
auto on_entity(const DdsEndpoint & dds, F && f) -> decltype(f(*dds.writer))
{
  GilRelease nogil;
  return dds.writer ? f(*dds.writer) : f(*dds.reader);
}

/// Parse `(endpoint, kind)` (`format` names the function), open the endpoint and return
/// `f(dds)` (nullptr with an exception when it cannot be opened).
template<typename F>
PyObject * with_endpoint(PyObject * args, const char * format, F && f)
{
  PyObject * endpoint_arg;
  const char * kind;
  PinnedHandle endpoint;
  DdsEndpoint dds;
  if (!PyArg_ParseTuple(args, format, &endpoint_arg, &kind) ||
    open_endpoint(endpoint_arg, kind, &endpoint, &dds) < 0)
  {
    return nullptr;
  }
  return f(dds);
}

PyObject * endpoint_gid(PyObject *, PyObject * args)
{
  return with_endpoint(args, "Os:endpoint_gid", [](const DdsEndpoint & dds) {
      uint8_t gid[RMW_GID_STORAGE_SIZE] = {};
      on_entity(dds, [&](auto & entity) {
          rmw_fastrtps_shared_cpp::copy_from_fastrtps_guid_to_byte_array(entity.guid(), gid);
        });
      return gid_bytes(gid);
    });
}

PyObject * get_user_data(PyObject *, PyObject * args)
{
  return with_endpoint(args, "Os:get_user_data", [](const DdsEndpoint & dds) {
      const std::vector<uint8_t> data = on_entity(dds, [](auto & entity) {
          return entity.get_qos().user_data().data_vec();
        });
      return PyBytes_FromStringAndSize(
        reinterpret_cast<const char *>(data.data()), static_cast<Py_ssize_t>(data.size()));
    });
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
  // USER_DATA travels in a parameter whose length is a uint16; keep well below it.
  if (data.size() > 32768) {
    PyErr_Format(PyExc_ValueError, "user_data too long (%zu bytes, at most 32768)", data.size());
    return nullptr;
  }
  PinnedHandle endpoint;
  DdsEndpoint dds;
  if (open_endpoint(endpoint_arg, kind, &endpoint, &dds) < 0) {
    return nullptr;
  }
  bool stored = false;
  // No lock of ours is held: set_qos() may run discovery callbacks synchronously.
  const ReturnCode_t rc = on_entity(dds, [&](auto & entity) {
      auto qos = entity.get_qos();
      qos.user_data().data_vec(data);
      const ReturnCode_t result = entity.set_qos(qos);
      stored = entity.get_qos().user_data().data_vec() == data;
      return result;
    });
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

/// hold_enabling(node, kind, hold): see the method table (GIL held throughout).
PyObject * hold_enabling(PyObject *, PyObject * args)
{
  PyObject * node_arg;
  const char * kind;
  int hold;
  if (!PyArg_ParseTuple(args, "Osp:hold_enabling", &node_arg, &kind, &hold)) {
    return nullptr;
  }
  const bool writers = std::strcmp(kind, "publisher") == 0;
  if (!writers && std::strcmp(kind, "subscription") != 0) {
    PyErr_Format(
      PyExc_ValueError, "kind must be 'publisher' or 'subscription', got '%s'", kind);
    return nullptr;
  }
  PinnedHandle node;
  rmw_node_t * rmw_node = pin_rmw_node(node_arg, &node);
  if (rmw_node == nullptr) {
    return nullptr;
  }
  std::string error;
  if (!rmw_private::hold_enabling(rmw_node, writers, hold != 0, &error)) {
    PyErr_Format(DdsError, "hold_enabling: %s", error.c_str());
    return nullptr;
  }
  Py_RETURN_NONE;
}

/// take_serialized_with_gid and take_message_with_gid: one serialized take from an rcl
/// subscription; with `support`, deserialized into a Python message when it can be: built by
/// `program` (a slot program, see codec_fast.cpp) where it builds it exactly, else by the type
/// support and convert_to_py.
PyObject * take_with_gid(
  PyObject * sub_arg, const MessageSupport * support, Py_ssize_t max_size,
  PyObject * program = nullptr)
{
  PinnedHandle sub;
  if (sub.acquire(sub_arg, "subscription") < 0) {
    return nullptr;
  }
  OwnedRosMessage ros_message(support);  // created only for a sample to deserialize
  rcl_serialized_message_t msg = rmw_get_zero_initialized_serialized_message();
  rmw_message_info_t info = rmw_get_zero_initialized_message_info();
  rcl_ret_t ret;
  bool deserialized = false;
  // (a program comes with `support`: take_message_with_gid passes both)
  const bool by_program = support != nullptr && program != nullptr && program != Py_None;
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
    } else if (ret == RCL_RET_OK && support != nullptr && fits(msg, max_size) && !by_program) {
      deserialized = try_deserialize(*support, msg, &ros_message);
    }
  }
  PyObject * result = nullptr;
  if (ret == RCL_RET_SUBSCRIPTION_TAKE_FAILED) {
    result = Py_NewRef(Py_None);
  } else if (ret != RCL_RET_OK) {
    raise_rmw_error("rcl_take_serialized_message failed", error);
  } else {
    // the slot program where it builds the message exactly (no Python setter per field), at
    // any length (it copies a payload once, the type support's conversion twice); else the
    // type support within max_size, as above without a program
    PyObject * built = build_from_cdr(program, msg.buffer, msg.buffer_length);
    if (built == nullptr && by_program && fits(msg, max_size)) {
      deserialized = without_gil([&] {return try_deserialize(*support, msg, &ros_message);});
    }
    result = taken_tuple(
      built ? built : deserialized ? support->to_py(ros_message.get()) : serialized_bytes(msg),
      info);
  }
  if (msg.buffer != nullptr) {
    GilRelease nogil;
    if (rmw_serialized_message_fini(&msg) != RMW_RET_OK) {
      rcutils_reset_error();
    }
  }
  return result;
}

PyObject * take_serialized_with_gid(PyObject *, PyObject * args)
{
  PyObject * sub_arg;
  if (!PyArg_ParseTuple(args, "O:take_serialized_with_gid", &sub_arg)) {
    return nullptr;
  }
  return take_with_gid(sub_arg, nullptr, -1);
}

PyObject * take_message_with_gid(PyObject *, PyObject * args)
{
  PyObject * sub_arg;
  PyObject * msg_class;
  Py_ssize_t max_size = -1;
  PyObject * program = Py_None;
  if (!PyArg_ParseTuple(
      args, "OO|nO:take_message_with_gid", &sub_arg, &msg_class, &max_size, &program))
  {
    return nullptr;
  }
  MessageSupport support;
  if (support.load(msg_class) < 0) {
    return nullptr;
  }
  return take_with_gid(sub_arg, &support, max_size, program);
}

/// The (writer GID, source timestamp in ns) of a sample's SampleInfo, as a Python tuple.
PyObject * sample_key(const eprosima::fastdds::dds::SampleInfo & info)
{
  uint8_t gid[RMW_GID_STORAGE_SIZE] = {};
  rmw_fastrtps_shared_cpp::copy_from_fastrtps_guid_to_byte_array(
    info.sample_identity.writer_guid(), gid);
  const int64_t ns = static_cast<int64_t>(info.source_timestamp.seconds()) * 1000000000LL +
    static_cast<int64_t>(info.source_timestamp.nanosec());
  return Py_BuildValue("(NL)", gid_bytes(gid), static_cast<long long>(ns));
}

/// `read(reader, &info)` on the DataReader of an rcl subscription (GIL released), then the
/// sample's key, or None when the call found no sample.
template<typename Read>
PyObject * sample_key_of(PyObject * sub_arg, Read && read)
{
  PinnedHandle sub;
  DdsEndpoint dds;
  if (sub.acquire(sub_arg, "subscription") < 0 || resolve_endpoint(sub.get(), false, &dds) < 0) {
    return nullptr;
  }
  eprosima::fastdds::dds::SampleInfo info;
  if (without_gil([&] {return read(*dds.reader, &info);}) != ReturnCode_t::RETCODE_OK) {
    Py_RETURN_NONE;
  }
  return sample_key(info);
}

/// peek_untaken(subscription) -> (publisher_gid, source_timestamp) | None: the next sample's
/// key, read from its SampleInfo (nothing is taken, nothing copied).
PyObject * peek_untaken(PyObject *, PyObject * sub_arg)
{
  return sample_key_of(sub_arg, [](DataReader & reader, eprosima::fastdds::dds::SampleInfo * info) {
      return reader.get_first_untaken_info(info);
    });
}

/// A cdr_deserialize that reads nothing: see discard_untaken.
bool skip_payload(eprosima::fastcdr::Cdr &, void *)
{
  return true;
}

/// Callbacks whose deserialization leaves the payload where Fast DDS received it.
const message_type_support_callbacks_t kSkipPayload = [] {
    message_type_support_callbacks_t callbacks{};
    callbacks.message_namespace_ = "rosidl_buffer_py";
    callbacks.message_name_ = "discarded";
    callbacks.cdr_deserialize = skip_payload;
    return callbacks;
  }();

/// discard_untaken(subscription) -> (publisher_gid, source_timestamp) | None: take the next
/// sample without copying its payload. rmw's type support deserializes a ROS message through
/// the callbacks the caller hands it in SerializedData::impl (rmw_fastrtps_shared_cpp's
/// TypeSupport::deserialize, FASTRTPS_SERIALIZED_DATA_TYPE_ROS_MESSAGE, over a FastBuffer that
/// views the received payload): ours read nothing, so the one sample leaves the reader and its
/// payload is released with it, never copied.
PyObject * discard_untaken(PyObject *, PyObject * sub_arg)
{
  return sample_key_of(sub_arg, [](DataReader & reader, eprosima::fastdds::dds::SampleInfo * info) {
      char unused = 0;
      rmw_fastrtps_shared_cpp::SerializedData data;
      data.type = rmw_fastrtps_shared_cpp::FASTRTPS_SERIALIZED_DATA_TYPE_ROS_MESSAGE;
      data.data = &unused;
      data.impl = &kSkipPayload;
      return reader.take_next_sample(&data, info);
    });
}

PyObject * publish_serialized(PyObject *, PyObject * args, PyObject * kwds)
{
  static const char * kwlist[] = {"publisher", "data", "source_timestamp", nullptr};
  PyObject * pub_arg;
  PyObject * data_arg;
  PyObject * ts_arg;
  if (!PyArg_ParseTupleAndKeywords(
      args, kwds, "OOO:publish_serialized", const_cast<char **>(kwlist),
      &pub_arg, &data_arg, &ts_arg))
  {
    return nullptr;
  }
  int64_t source_timestamp;
  if (check_handle_kind(pub_arg, "Publisher", "publisher") < 0 ||
    parse_source_timestamp(ts_arg, &source_timestamp) < 0)
  {
    return nullptr;
  }
  SerializedView view;
  PinnedHandle pub;
  DdsEndpoint dds;
  if (view.acquire(data_arg) < 0 || pub.acquire(pub_arg, "publisher") < 0 ||
    resolve_endpoint(pub.get(), true, &dds) < 0)
  {
    return nullptr;
  }
  std::string error;
  // The pin keeps the rcl publisher (and its DataWriter) alive; Fast DDS copies the bytes.
  if (!without_gil([&] {
      if (!write_serialized_w_timestamp(
          dds.writer, view.data(), view.size(), source_timestamp, &error))
      {
        return false;
      }
      gap_to_excluded_readers(dds.writer);  // the main topic's writer
      return true;
    }))
  {
    PyErr_Format(DdsError, "publish_serialized: %s", error.c_str());
    return nullptr;
  }
  Py_RETURN_NONE;
}

/// `call(rmw_publisher, &error)` on a pinned rclpy publisher, GIL released; false with
/// DdsError("<what>: <error>") when it fails.
template<typename Call>
bool on_rmw_publisher(PyObject * pub_arg, const char * what, Call && call)
{
  PinnedHandle pub;
  rmw_publisher_t * rmw_pub = pin_rmw_publisher(pub_arg, "publisher", &pub);
  if (rmw_pub == nullptr) {
    return false;
  }
  std::string error;
  if (!without_gil([&] {return call(rmw_pub, &error);})) {
    PyErr_Format(DdsError, "%s: %s", what, error.c_str());
    return false;
  }
  return true;
}

PyObject * matched_subscription_gids(PyObject *, PyObject * pub_arg)
{
  std::vector<GidArray> gids;
  if (!on_rmw_publisher(pub_arg, "matched_subscription_gids",
    [&](rmw_publisher_t * pub, std::string * error) {
      return matched_reader_gids(pub, &gids, error);
    }))
  {
    return nullptr;
  }
  return gid_list(gids);
}

PyObject * exclude_from_next_write(PyObject *, PyObject * args)
{
  PyObject * pub_arg;
  PyObject * gids_arg;
  if (!PyArg_ParseTuple(args, "OO:exclude_from_next_write", &pub_arg, &gids_arg)) {
    return nullptr;
  }
  PyObject * gids_seq = PySequence_Fast(gids_arg, "reader_gids must be a sequence of bytes");
  if (gids_seq == nullptr) {
    return nullptr;
  }
  std::vector<GidArray> readers(static_cast<size_t>(PySequence_Fast_GET_SIZE(gids_seq)));
  for (Py_ssize_t i = 0; i < PySequence_Fast_GET_SIZE(gids_seq); ++i) {
    PyObject * item = PySequence_Fast_GET_ITEM(gids_seq, i);
    char * data;
    Py_ssize_t length;
    if (!PyBytes_Check(item) || PyBytes_AsStringAndSize(item, &data, &length) < 0 ||
      length != RMW_GID_STORAGE_SIZE)
    {
      PyErr_Format(
        PyExc_ValueError, "reader_gids[%zd] must be %d bytes, got %R", i,
        static_cast<int>(RMW_GID_STORAGE_SIZE), item);
      Py_DECREF(gids_seq);
      return nullptr;
    }
    std::copy(data, data + length, readers[static_cast<size_t>(i)].begin());
  }
  Py_DECREF(gids_seq);
  bool available = false;
  if (!on_rmw_publisher(pub_arg, "exclude_from_next_write",
    [&](rmw_publisher_t * pub, std::string * error) {
      return rbpy_dds::exclude_from_next_write(pub, readers, &available, error);
    }))
  {
    return nullptr;
  }
  return PyBool_FromLong(available);
}

PyObject * remove_write_exclusions(PyObject *, PyObject * pub_arg)
{
  if (!on_rmw_publisher(pub_arg, "remove_write_exclusions", rbpy_dds::remove_write_exclusions)) {
    return nullptr;
  }
  Py_RETURN_NONE;
}

// ---- new-message wakeups on rcl subscriptions ----

/// One registration: the user data of rmw's on-new-message callback. Immutable while
/// registered; deleted (pins released, GIL held) only after rmw no longer calls it.
struct NewMessageWakeup
{
  rcl_guard_condition_t * guard_condition = nullptr;
  PinnedHandle guard_condition_pin;
  PinnedHandle subscription_pin;  // released last: may run rclpy's deferred destroy
  ~NewMessageWakeup()
  {
    guard_condition_pin.release();
    subscription_pin.release();
  }
};

/// rcl subscription -> its registration. Leaked on purpose (no static destruction at exit).
/// `mutex` serialises set/clear and is held across rcl_subscription_set_on_new_message_callback
/// (which may run the callback synchronously); the callback itself never takes it.
struct NewMessageWakeups
{
  std::mutex mutex;
  std::map<const rcl_subscription_t *, NewMessageWakeup *> entries;
};

NewMessageWakeups & new_message_wakeups()
{
  static NewMessageWakeups * w = new NewMessageWakeups();
  return *w;
}

/// Runs on a DDS thread (or synchronously inside set) under rmw's callback mutex: no Python,
/// no lock of ours; rcl_trigger_guard_condition only sets a flag and notifies waiters.
void on_new_message_wakeup(const void * user_data, size_t number_of_events)
{
  (void)number_of_events;
  auto * wakeup = static_cast<const NewMessageWakeup *>(user_data);
  if (rcl_trigger_guard_condition(wakeup->guard_condition) != RCL_RET_OK) {
    rcl_reset_error();
  }
}

PyObject * set_new_message_wakeup(PyObject *, PyObject * args)
{
  PyObject * sub_arg;
  PyObject * gc_arg;
  if (!PyArg_ParseTuple(args, "OO:set_new_message_wakeup", &sub_arg, &gc_arg)) {
    return nullptr;
  }
  if (check_handle_kind(sub_arg, "Subscription", "subscription") < 0 ||
    check_handle_kind(gc_arg, "GuardCondition", "guard_condition") < 0)
  {
    return nullptr;
  }
  auto * wakeup = new NewMessageWakeup();
  if (wakeup->subscription_pin.acquire(sub_arg, "subscription") < 0 ||
    wakeup->guard_condition_pin.acquire(gc_arg, "guard_condition") < 0)
  {
    delete wakeup;
    return nullptr;
  }
  wakeup->guard_condition =
    static_cast<rcl_guard_condition_t *>(wakeup->guard_condition_pin.get());
  auto * sub = static_cast<const rcl_subscription_t *>(wakeup->subscription_pin.get());
  NewMessageWakeup * previous = nullptr;
  rcl_ret_t ret;
  std::string error;
  {
    GilRelease nogil;
    NewMessageWakeups & reg = new_message_wakeups();
    std::lock_guard<std::mutex> lock(reg.mutex);
    // rmw may call the callback right here (with the count of unread messages). Replacing a
    // registration is a barrier too: rmw swaps callbacks under the mutex it calls them with.
    ret = rcl_subscription_set_on_new_message_callback(sub, on_new_message_wakeup, wakeup);
    if (ret == RCL_RET_OK) {
      NewMessageWakeup *& slot = reg.entries[sub];
      previous = slot;
      slot = wakeup;
    } else {
      error = take_rmw_error();
    }
  }
  if (ret != RCL_RET_OK) {
    delete wakeup;  // never registered
    return raise_rmw_error("rcl_subscription_set_on_new_message_callback failed", error);
  }
  delete previous;  // no longer called: release its pins (GIL held)
  Py_RETURN_NONE;
}

PyObject * clear_new_message_wakeup(PyObject *, PyObject * sub_arg)
{
  if (check_handle_kind(sub_arg, "Subscription", "subscription") < 0) {
    return nullptr;
  }
  // Only peek: rclpy may already have been asked to destroy the subscription (our pin
  // deferred it), and entering it again would raise.
  auto * sub = static_cast<const rcl_subscription_t *>(
    PinnedHandle::peek(sub_arg, "subscription"));
  if (sub == nullptr) {
    if (!PyLong_Check(sub_arg) && PyErr_ExceptionMatches(PyExc_ValueError)) {
      // A handle rclpy already destroyed: set pins what it registers, so nothing is set.
      PyErr_Clear();
      Py_RETURN_NONE;
    }
    return nullptr;
  }
  NewMessageWakeup * wakeup = nullptr;
  rcl_ret_t ret = RCL_RET_OK;
  std::string error;
  {
    GilRelease nogil;
    NewMessageWakeups & reg = new_message_wakeups();
    std::lock_guard<std::mutex> lock(reg.mutex);
    auto it = reg.entries.find(sub);
    if (it != reg.entries.end()) {
      // rmw holds its callback mutex while calling us: once this returns, the callback is
      // neither running nor will it run again.
      ret = rcl_subscription_set_on_new_message_callback(sub, nullptr, nullptr);
      if (ret == RCL_RET_OK) {
        wakeup = it->second;
        reg.entries.erase(it);
      } else {
        error = take_rmw_error();
      }
    }
  }
  if (ret != RCL_RET_OK) {
    // Still registered (and pinned): freeing it could leave rmw with a dangling pointer.
    return raise_rmw_error("rcl_subscription_set_on_new_message_callback(NULL) failed", error);
  }
  delete wakeup;  // unpin the guard condition, then the subscription (GIL held)
  Py_RETURN_NONE;
}

}  // namespace

PyMethodDef endpoint_functions[] = {
  RBPY_FUNCTION(endpoint_gid, METH_VARARGS,
    "endpoint_gid(endpoint, kind) -> bytes\n\n"
    "The 16-byte GID of an rcl publisher/subscription (kind 'publisher'/'subscription'), as\n"
    "Node.get_publishers_info_by_topic() reports it in endpoint_gid."),
  RBPY_FUNCTION(get_user_data, METH_VARARGS,
    "get_user_data(endpoint, kind) -> bytes\n\n"
    "The USER_DATA QoS of the DataWriter/DataReader behind an rcl publisher/subscription."),
  RBPY_FUNCTION(set_user_data, METH_VARARGS,
    "set_user_data(endpoint, kind, data: bytes) -> None\n\n"
    "Replace that USER_DATA (keep rmw's 'typehash=...;' prefix!). Remote participants see\n"
    "the change as a 'changed' discovery event."),
  RBPY_FUNCTION(hold_enabling, METH_VARARGS,
    "hold_enabling(node, kind, hold: bool) -> None\n\n"
    "While held, the DataWriters (kind 'publisher') or DataReaders ('subscription') that rmw\n"
    "creates with the node's participant are created disabled, so that their USER_DATA is set\n"
    "before discovery announces them; letting go (hold False) enables every one of them."),
  RBPY_FUNCTION(take_message_with_gid, METH_VARARGS,
    "take_message_with_gid(subscription, msg_class, max_size=-1, program=None) -> (message | "
    "bytes, publisher_gid, info) | None\n\nAs take_serialized_with_gid, but the CDR is "
    "deserialized into a msg_class instance as rclpy's take does (built by `program`, a slot "
    "program of codec/plans.py, at any length where it can: the same message); CDR that does "
    "not deserialize (a descriptor payload, malformed data), or that the type support would "
    "have to deserialize and is longer than max_size bytes when max_size >= 0, comes back as "
    "bytes."),
  RBPY_FUNCTION(peek_untaken, METH_O,
    "peek_untaken(subscription) -> (publisher_gid, source_timestamp) | None\n\n"
    "The next unread sample's publisher GID and source timestamp (ns), from its SampleInfo:\n"
    "nothing is taken or copied."),
  RBPY_FUNCTION(discard_untaken, METH_O,
    "discard_untaken(subscription) -> (publisher_gid, source_timestamp) | None\n\n"
    "Take the next unread sample without copying its payload (a duplicate to drop)."),
  RBPY_FUNCTION(take_serialized_with_gid, METH_VARARGS,
    "take_serialized_with_gid(subscription) -> (bytes, publisher_gid, info) | None\n\n"
    "rcl_take_serialized_message on an rcl subscription: the CDR bytes, the 16-byte GID of\n"
    "the publisher and an rclpy-like message info dict; None when nothing is there."),
  RBPY_FUNCTION(publish_serialized, METH_VARARGS | METH_KEYWORDS,
    "publish_serialized(publisher, data, source_timestamp: int) -> None\n\n"
    "Write serialized CDR (with its 4-byte encapsulation header; any C-contiguous buffer,\n"
    "not copied in Python) on the DataWriter behind an rcl publisher, with an explicit\n"
    "source timestamp in ns since the epoch (takes report it in info['source_timestamp'])."),
  RBPY_FUNCTION(matched_subscription_gids, METH_O,
    "matched_subscription_gids(publisher) -> list[bytes]\n\n"
    "16-byte GIDs (as get_subscriptions_info_by_topic endpoint_gid) of the DataReaders\n"
    "currently matched with the DataWriter behind an rcl publisher."),
  RBPY_FUNCTION(exclude_from_next_write, METH_VARARGS,
    "exclude_from_next_write(publisher, reader_gids) -> bool\n\n"
    "Keep the next sample written on the DataWriter behind an rcl publisher from the matched\n"
    "DataReaders reader_gids (16-byte GIDs): Fast DDS sends them a GAP instead, so they\n"
    "neither receive nor copy it. Call right before the write; calling again before it\n"
    "replaces the set. False when this writer cannot filter (then nothing is excluded)."),
  RBPY_FUNCTION(remove_write_exclusions, METH_O,
    "remove_write_exclusions(publisher) -> None\n\n"
    "Take the exclusion filter off the publisher's DataWriter (before destroying it)."),
  RBPY_FUNCTION(set_new_message_wakeup, METH_VARARGS,
    "set_new_message_wakeup(subscription, guard_condition) -> None\n\n"
    "Trigger the rcl guard condition on every new message of the rcl subscription\n"
    "(rcl_subscription_set_on_new_message_callback; also right away if messages are\n"
    "unread). Replaces an earlier registration. Pins both until clear_new_message_wakeup()."),
  RBPY_FUNCTION(clear_new_message_wakeup, METH_O,
    "clear_new_message_wakeup(subscription) -> None\n\n"
    "Stop triggering (a barrier: once it returns, the guard condition is never triggered by\n"
    "it again) and unpin both. No-op when nothing is registered (also on a handle rclpy\n"
    "already destroyed). Works after rclpy was asked to destroy the subscription."),
  RBPY_METHODS_END,
};

}  // namespace rbpy_dds
