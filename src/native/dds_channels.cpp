// Per-endpoint channels below rcl: an rmw publisher/subscription on the node's rmw handle,
// created with avoid_ros_namespace_conventions (so the given name is the DDS topic name and
// rcl's name rules, e.g. "no token starting with a digit", do not apply), volatile
// durability, and exchanging pre-serialized CDR.
//
//   ChannelPublisher(node, type_support, topic_name, reliability=1, history=1, depth=10)
//     .publish(data, source_timestamp=None)  any C-contiguous buffer; GIL released during
//                               the write; an int timestamp (ns) goes through the DataWriter
//     .matched_count() -> int   matched subscriptions
//     .matched_gids() -> list[bytes]  GIDs of the matched DataReaders
//     .gid, .topic_name, .valid
//     .destroy()
//   ChannelSubscription(node, type_support, topic_name, reliability=1, history=1, depth=10,
//                       guard_condition=None)
//     .take() -> (bytes, publisher_gid, info) | None
//     .take_described(msg_class, prefix_ops, suffix_size, max_descriptor, program=None)
//         -> (bytes, publisher_gid, info, (message, backend_type, descriptor) | None) | None
//     .take_message(msg_class, max_size=-1) -> (message | bytes, publisher_gid, info) | None
//     .matched_count() -> int   matched publishers
//     .gid, .topic_name, .valid, .on_udp (listens on UDP only: see "channel transport" below)
//     .destroy()
//
//   write_message(message, source_timestamp, targets, program=None, descriptor=None)
//       convert once (from the slots by a slot program where it can), write to each target
//       (ChannelPublisher or rclpy Publisher) with that timestamp; with a descriptor, the
//       descriptor form from the slots to channels (False when the program cannot)
//
// Both pin the node's rclpy handle (rclpy defers destroy_node() until destroy()) and the
// subscription pins its guard condition, which it triggers from the DDS thread (rmw's
// on-new-message callback) whenever data arrives.
#include <atomic>
#include <cstdlib>
#include <cstring>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include "dds_common.hpp"
#include "dds_writer.hpp"
#include "rmw_fastrtps_private.hpp"

#include "rcl/error_handling.h"
#include "rcutils/error_handling.h"
#include "rcl/guard_condition.h"
#include "rcl/node.h"
#include "rcl/publisher.h"
#include "rmw/rmw.h"
#include "rmw/serialized_message.h"
#include "rosidl_runtime_c/message_type_support_struct.h"
#include "fastdds/dds/subscriber/DataReader.hpp"
#include "fastdds/dds/subscriber/Subscriber.hpp"
#include "fastdds/dds/subscriber/qos/DataReaderQos.hpp"
#include "fastdds/rtps/common/Locator.h"
#include "fastdds/rtps/common/LocatorList.hpp"
#include "rmw_fastrtps_cpp/get_publisher.hpp"
#include "rmw_fastrtps_cpp/get_subscriber.hpp"
#include "rmw_fastrtps_shared_cpp/guid_utils.hpp"

namespace rbpy_dds
{
namespace
{

/// What the rmw on-new-message callback needs; lives until the callback is unset.
struct NewMessageNotify
{
  explicit NewMessageNotify(rcl_guard_condition_t * gc)
  : guard_condition(gc) {}

  rcl_guard_condition_t * guard_condition;
  /// Samples announced by the callback and not taken since: never fewer than the announced
  /// samples still in the reader (a take of a sample not announced yet clamps at 0, and its
  /// announcement later over-counts, which costs one empty take), reset by a take that finds
  /// none. So `pending() == 0` means that every sample still unread will trigger, or has
  /// triggered since, the guard condition: a channel with nothing pending need not be taken.
  std::atomic<uint64_t> notified{0};

  /// After a take: `any` when it found a sample; `seen` is the count read before it. An empty
  /// take forgets only what was announced before it: an announcement that came in meanwhile
  /// (its sample may have landed after the take looked) stays pending.
  void taken(bool any, uint64_t seen)
  {
    if (!any) {
      notified.compare_exchange_strong(seen, 0);
      return;
    }
    uint64_t value = notified.load();
    while (value > 0 && !notified.compare_exchange_weak(value, value - 1)) {
    }
  }
};

void on_new_message(const void * user_data, size_t number_of_events)
{
  auto * notify = const_cast<NewMessageNotify *>(static_cast<const NewMessageNotify *>(user_data));
  notify->notified.fetch_add(number_of_events);  // before the trigger: the woken side sees it
  if (rcl_trigger_guard_condition(notify->guard_condition) != RCL_RET_OK) {
    rcl_reset_error();
  }
}

// ------------------------------------------------------------------ channel transport
//
// A channel subscription's DataReader listens on UDP only (loopback on one host), not on the
// participant's shared-memory locator: measured (issue #19, src/native/README.md "Channel
// transport"), a channel sample sent over Fast DDS's SHM transport beside main-topic traffic is
// lost and repaired up to a second later. The publisher's participant has ONE SHM segment
// (512 KB by default) for everything it sends; a main-topic frame larger than that (640x480
// rgb8 is 15 fragments, 921 KB) makes each fragment's allocation recycle the oldest buffers not
// yet taken by their receiver, among them the descriptor written just before, still queued
// in the buffer-aware subscriber's port. Its reader then waits for a heartbeat to learn of the
// loss, and keeps every later descriptor back until the repair arrives (in-order delivery).
// UDP datagrams do not go through that segment.
//
// How: rmw_create_subscription starts from its Subscriber's default DataReaderQos; for the
// channel's creation that default gets one unicast locator, UDPv4 "any" with port 0, which
// Fast DDS expands to the participant's own UDPv4 addresses and default user-traffic port (the
// receiver it already has). Only when the default names no locators (a user's XML profile that
// does is left alone), and only if the reader then listens on UDPv4; otherwise the
// subscription is created again with the participant's locators, as before.
// ROSIDL_BUFFER_PY_CHANNEL_TRANSPORT=participant turns this off (for comparisons).

bool channel_transport_udp()
{
  const char * value = std::getenv("ROSIDL_BUFFER_PY_CHANNEL_TRANSPORT");
  return value == nullptr || std::strcmp(value, "participant") != 0;
}

bool listens_on_udp_only(rmw_subscription_t * subscription)
{
  eprosima::fastdds::dds::DataReader * reader = rmw_fastrtps_cpp::get_datareader(subscription);
  eprosima::fastdds::rtps::LocatorList locators;
  if (reader == nullptr || reader->get_listening_locators(locators) !=
    eprosima::fastrtps::types::ReturnCode_t::RETCODE_OK || locators.empty())
  {
    return false;
  }
  for (const auto & locator : locators) {
    if (locator.kind != LOCATOR_KIND_UDPv4) {
      return false;
    }
  }
  return true;
}

/// rmw_create_subscription for a channel (GIL held: rclpy creates its entities with the GIL
/// held, so no rclpy thread creates a DataReader while the default QoS is changed).
/// `*on_udp` tells whether the reader listens on UDP only.
rmw_subscription_t * create_channel_subscription(
  rmw_node_t * node, const rosidl_message_type_support_t * ts, const char * topic_name,
  const rmw_qos_profile_t * qos, const rmw_subscription_options_t * options, bool * on_udp)
{
  *on_udp = false;
  std::string error;
  eprosima::fastdds::dds::Subscriber * subscriber =
    channel_transport_udp() ? rmw_private::rmw_subscriber_of(node, &error) : nullptr;
  if (subscriber != nullptr) {
    static std::mutex creation_mutex;  // our own creations, from threads without the GIL
    std::lock_guard<std::mutex> lock(creation_mutex);
    const eprosima::fastdds::dds::DataReaderQos saved = subscriber->get_default_datareader_qos();
    if (saved.endpoint().unicast_locator_list.empty() &&
      saved.endpoint().multicast_locator_list.empty())
    {
      eprosima::fastdds::dds::DataReaderQos udp = saved;
      eprosima::fastrtps::rtps::Locator_t any;  // UDPv4, address 0.0.0.0, port 0
      any.kind = LOCATOR_KIND_UDPv4;
      any.port = 0;
      udp.endpoint().unicast_locator_list.push_back(any);
      if (subscriber->set_default_datareader_qos(udp) ==
        eprosima::fastrtps::types::ReturnCode_t::RETCODE_OK)
      {
        rmw_subscription_t * subscription = rmw_create_subscription(
          node, ts, topic_name, qos, options);
        subscriber->set_default_datareader_qos(saved);
        if (subscription != nullptr && listens_on_udp_only(subscription)) {
          *on_udp = true;
          return subscription;
        }
        if (subscription != nullptr &&
          rmw_destroy_subscription(node, subscription) != RMW_RET_OK)
        {
          rcutils_reset_error();
        }
        rcutils_reset_error();
      }
    }
  }
  return rmw_create_subscription(node, ts, topic_name, qos, options);
}

/// Fields shared by both channel types.
struct ChannelBase
{
  PyObject_HEAD
  PinnedHandle * node;          // owned
  rmw_node_t * rmw_node;
  std::mutex * op_mutex;        // owned; serialises operations against destroy()
  uint8_t gid[RMW_GID_STORAGE_SIZE];
  std::string * topic_name;     // owned
};

struct ChannelPublisherObject
{
  ChannelBase base;
  rmw_publisher_t * publisher;  // nullptr once destroyed
};

struct ChannelSubscriptionObject
{
  ChannelBase base;
  rmw_subscription_t * subscription;  // nullptr once destroyed
  PinnedHandle * guard_condition;     // owned; may hold nothing
  NewMessageNotify * notify;          // owned; nullptr without guard condition
  rmw_serialized_message_t * buffer;  // owned; reused by take()
  bool on_udp;                        // the DataReader listens on UDP only
};

int base_alloc(ChannelBase * base)
{
  base->node = new (std::nothrow) PinnedHandle();
  base->op_mutex = new (std::nothrow) std::mutex();
  base->topic_name = new (std::nothrow) std::string();
  base->rmw_node = nullptr;
  std::memset(base->gid, 0, sizeof(base->gid));
  if (!base->node || !base->op_mutex || !base->topic_name) {
    PyErr_NoMemory();
    return -1;
  }
  return 0;
}

void base_free(ChannelBase * base)
{
  delete base->node;  // releases the pin (GIL held)
  delete base->op_mutex;
  delete base->topic_name;
  base->node = nullptr;
  base->op_mutex = nullptr;
  base->topic_name = nullptr;
}

/// Common constructor part: pin the node, check the rmw, read the type support.
int base_setup(
  ChannelBase * base, PyObject * node_arg, PyObject * type_support_arg, const char * topic_name,
  int reliability, int history, int depth, const rosidl_message_type_support_t ** type_support,
  rmw_qos_profile_t * qos)
{
  if (base->rmw_node != nullptr) {
    PyErr_SetString(PyExc_RuntimeError, "channel is already initialized");
    return -1;
  }
  if (!PyCapsule_CheckExact(type_support_arg)) {
    PyErr_Format(
      PyExc_TypeError, "type_support must be a message type's _TYPE_SUPPORT capsule, got %.100s "
      "(call msg_type.__class__.__import_type_support__() first)",
      Py_TYPE(type_support_arg)->tp_name);
    return -1;
  }
  *type_support = static_cast<const rosidl_message_type_support_t *>(
    PyCapsule_GetPointer(type_support_arg, PyCapsule_GetName(type_support_arg)));
  if (*type_support == nullptr) {
    return -1;
  }
  if (topic_name[0] == '\0') {
    PyErr_SetString(PyExc_ValueError, "topic_name must not be empty");
    return -1;
  }
  if (reliability < 0 || reliability > 2 || history < 0 || history > 2 || depth < 0) {
    PyErr_Format(
      PyExc_ValueError, "bad QoS: reliability=%d history=%d depth=%d (rmw enum values: "
      "reliability 1 reliable / 2 best effort, history 1 keep last / 2 keep all)",
      reliability, history, depth);
    return -1;
  }
  if (base->node->acquire(node_arg, "node") < 0) {
    return -1;
  }
  rmw_node_t * rmw_node = fastrtps_handle(base->node->get(), rcl_node_get_rmw_handle, "node");
  if (rmw_node == nullptr) {
    base->node->release();
    return -1;
  }
  *qos = rmw_qos_profile_default;
  qos->reliability = static_cast<rmw_qos_reliability_policy_t>(reliability);
  qos->history = static_cast<rmw_qos_history_policy_t>(history);
  qos->depth = static_cast<size_t>(depth);
  qos->durability = RMW_QOS_POLICY_DURABILITY_VOLATILE;
  qos->avoid_ros_namespace_conventions = true;
  base->topic_name->assign(topic_name);
  base->rmw_node = rmw_node;
  return 0;
}

/// Undo base_setup after a failed creation (GIL held).
void base_unsetup(ChannelBase * base)
{
  base->rmw_node = nullptr;
  base->node->release();
}

PyObject * base_gid(PyObject * self, void *)
{
  return gid_bytes(reinterpret_cast<ChannelBase *>(self)->gid);
}

PyObject * base_topic_name(PyObject * self, void *)
{
  const std::string & name = *reinterpret_cast<ChannelBase *>(self)->topic_name;
  return PyUnicode_FromStringAndSize(name.data(), static_cast<Py_ssize_t>(name.size()));
}

/// Parse the constructor's arguments (ChannelSubscription's also takes `guard_condition`)
/// and run base_setup. Returns 0, or -1 with an exception set.
int channel_init_args(
  ChannelBase * base, PyObject * args, PyObject * kwds, PyObject ** gc_arg,
  const rosidl_message_type_support_t ** type_support, rmw_qos_profile_t * qos)
{
  static const char * subscription_kwlist[] = {
    "node", "type_support", "topic_name", "reliability", "history", "depth", "guard_condition",
    nullptr};
  static const char * publisher_kwlist[] = {
    "node", "type_support", "topic_name", "reliability", "history", "depth", nullptr};
  PyObject * node_arg;
  PyObject * ts_arg;
  const char * topic_name;
  int reliability = RMW_QOS_POLICY_RELIABILITY_RELIABLE;
  int history = RMW_QOS_POLICY_HISTORY_KEEP_LAST;
  int depth = 10;
  if (!PyArg_ParseTupleAndKeywords(
      args, kwds, gc_arg ? "OOs|iiiO:ChannelSubscription" : "OOs|iii:ChannelPublisher",
      const_cast<char **>(gc_arg ? subscription_kwlist : publisher_kwlist), &node_arg, &ts_arg,
      &topic_name, &reliability, &history, &depth, gc_arg))
  {
    return -1;
  }
  return base_setup(
    base, node_arg, ts_arg, topic_name, reliability, history, depth, type_support, qos);
}

/// The rmw entity of a channel object (nullptr once destroyed).
rmw_publisher_t *& entity(ChannelPublisherObject * self) {return self->publisher;}
rmw_subscription_t *& entity(ChannelSubscriptionObject * self) {return self->subscription;}
const char * type_name(ChannelPublisherObject *) {return "ChannelPublisher";}
const char * type_name(ChannelSubscriptionObject *) {return "ChannelSubscription";}

/// `op(entity, &error)` with the GIL released, serialised against destroy() by the channel's
/// mutex; DdsError "<type> was destroyed" once it is. False with the exception set.
template<typename Object, typename Op>
bool channel_call(Object * self, Op && op)
{
  PendingError error;
  {
    GilRelease nogil;
    std::lock_guard<std::mutex> lock(*self->base.op_mutex);
    if (entity(self) == nullptr) {
      error.set(DdsError, std::string(type_name(self)) + " was destroyed");
    } else {
      op(entity(self), &error);
    }
  }
  return error ? error.raise() != nullptr : true;
}

/// destroy(): `destroy_rmw(entity, &error)` once (GIL released, under the channel's mutex),
/// then `unpin()` and the node's pin released (GIL held: the rmw entity is gone by then).
/// Returns 0 or -1 with an exception set.
template<typename Object, typename DestroyRmw, typename Unpin>
int destroy_channel(Object * self, DestroyRmw && destroy_rmw, Unpin && unpin)
{
  if (self->base.op_mutex == nullptr) {
    return 0;
  }
  PendingError error;
  bool destroyed = false;
  {
    GilRelease nogil;
    std::lock_guard<std::mutex> lock(*self->base.op_mutex);
    if (entity(self) != nullptr) {
      destroy_rmw(entity(self), &error);
      entity(self) = nullptr;
      destroyed = true;
    }
  }
  if (destroyed) {
    unpin();
    base_unsetup(&self->base);
  }
  return error ? (error.raise(), -1) : 0;
}

int do_destroy(ChannelPublisherObject * self);
int do_destroy(ChannelSubscriptionObject * self);
void free_members(ChannelPublisherObject *) {}
void free_members(ChannelSubscriptionObject * self);

/// tp_new: the object zeroed (tp_alloc), with its base's members allocated.
template<typename Object>
PyObject * channel_new(PyTypeObject * type, PyObject *, PyObject *)
{
  auto * self = reinterpret_cast<Object *>(type->tp_alloc(type, 0));
  if (self != nullptr && base_alloc(&self->base) < 0) {
    Py_DECREF(self);
    return nullptr;
  }
  return reinterpret_cast<PyObject *>(self);
}

/// tp_dealloc: destroy() (an error is reported as unraisable), then free.
template<typename Object>
void channel_dealloc(PyObject * op)
{
  auto * self = reinterpret_cast<Object *>(op);
  {
    rbpy_glue::SavedException saved;
    if (do_destroy(self) < 0) {
      PyErr_WriteUnraisable(op);
    }
  }
  free_members(self);
  base_free(&self->base);
  PyTypeObject * tp = Py_TYPE(op);
  tp->tp_free(op);
  Py_DECREF(tp);
}

template<typename Object>
PyObject * channel_destroy(PyObject * op, PyObject *)
{
  if (do_destroy(reinterpret_cast<Object *>(op)) < 0) {
    return nullptr;
  }
  Py_RETURN_NONE;
}

template<typename Object>
PyObject * channel_valid(PyObject * op, void *)
{
  return PyBool_FromLong(entity(reinterpret_cast<Object *>(op)) != nullptr);
}

/// Matched count of a channel's rmw entity (`count_fn`, the rmw call that counts).
template<typename Object, typename Entity>
PyObject * matched_count(
  PyObject * op, rmw_ret_t (* count_fn)(const Entity *, size_t *), const char * call_name)
{
  size_t count = 0;
  if (!channel_call(reinterpret_cast<Object *>(op), [&](Entity * rmw_entity, PendingError * error) {
      if (count_fn(rmw_entity, &count) != RMW_RET_OK) {
        set_rmw_error(error, std::string(call_name) + " failed");
      }
    }))
  {
    return nullptr;
  }
  return PyLong_FromSize_t(count);
}

/// The getters both channel types have.
#define RBPY_CHANNEL_GETSET(Object, gid_doc) \
  {"gid", base_gid, nullptr, gid_doc, nullptr}, \
  {"topic_name", base_topic_name, nullptr, "DDS topic name", nullptr}, \
  {"valid", channel_valid<Object>, nullptr, "False once destroyed", nullptr}

/// The slots and the spec (`prefix`_slots, `prefix`_spec) of a channel type.
#define RBPY_CHANNEL_TYPE(prefix, Object, name, doc) \
  PyType_Slot prefix ## _slots[] = { \
    {Py_tp_doc, const_cast<char *>(doc)}, \
    {Py_tp_new, reinterpret_cast<void *>(channel_new<Object>)}, \
    {Py_tp_init, reinterpret_cast<void *>(prefix ## _init)}, \
    {Py_tp_dealloc, reinterpret_cast<void *>(channel_dealloc<Object>)}, \
    {Py_tp_methods, prefix ## _methods}, {Py_tp_getset, prefix ## _getset}, {0, nullptr}}; \
  PyType_Spec prefix ## _spec = { \
    "rosidl_buffer_py._native." name, sizeof(Object), 0, Py_TPFLAGS_DEFAULT, prefix ## _slots}

// ------------------------------------------------------------------ ChannelPublisher

int pub_init(PyObject * op, PyObject * args, PyObject * kwds)
{
  auto * self = reinterpret_cast<ChannelPublisherObject *>(op);
  const rosidl_message_type_support_t * ts;
  rmw_qos_profile_t qos;
  if (channel_init_args(&self->base, args, kwds, nullptr, &ts, &qos) < 0) {
    return -1;
  }
  rmw_publisher_options_t options = rmw_get_default_publisher_options();
  rmw_publisher_t * publisher;
  rmw_gid_t gid;
  std::string error;
  {
    GilRelease nogil;
    publisher = rmw_create_publisher(
      self->base.rmw_node, ts, self->base.topic_name->c_str(), &qos, &options);
    if (publisher == nullptr) {
      error = take_rmw_error();
    } else if (rmw_get_gid_for_publisher(publisher, &gid) != RMW_RET_OK) {
      error = take_rmw_error();
      if (rmw_destroy_publisher(self->base.rmw_node, publisher) != RMW_RET_OK) {
        rcutils_reset_error();
      }
      publisher = nullptr;
    }
  }
  if (publisher == nullptr) {
    base_unsetup(&self->base);
    raise_rmw_error("rmw_create_publisher('" + *self->base.topic_name + "') failed", error);
    return -1;
  }
  std::memcpy(self->base.gid, gid.data, RMW_GID_STORAGE_SIZE);
  self->publisher = publisher;
  return 0;
}

int do_destroy(ChannelPublisherObject * self)
{
  return destroy_channel(self, [self](rmw_publisher_t * publisher, PendingError * error) {
      if (rmw_destroy_publisher(self->base.rmw_node, publisher) != RMW_RET_OK) {
        set_rmw_error(error, "rmw_destroy_publisher failed");
      }
    }, [] {});
}

PyObject * pub_publish(PyObject * op, PyObject * args, PyObject * kwds)
{
  static const char * kwlist[] = {"data", "source_timestamp", nullptr};
  auto * self = reinterpret_cast<ChannelPublisherObject *>(op);
  PyObject * data;
  PyObject * ts_arg = Py_None;
  if (!PyArg_ParseTupleAndKeywords(
      args, kwds, "O|O:publish", const_cast<char **>(kwlist), &data, &ts_arg))
  {
    return nullptr;
  }
  const bool with_timestamp = ts_arg != Py_None;
  int64_t source_timestamp = 0;
  if (with_timestamp && parse_source_timestamp(ts_arg, &source_timestamp) < 0) {
    return nullptr;
  }
  SerializedView view;
  if (view.acquire(data) < 0) {
    return nullptr;
  }
  if (!channel_call(self, [&](rmw_publisher_t * publisher, PendingError * error) {
      if (with_timestamp) {
        // Same payload as rmw's serialized path, but with the caller's source timestamp.
        eprosima::fastdds::dds::DataWriter * writer = rmw_fastrtps_cpp::get_datawriter(publisher);
        std::string why = "rmw_fastrtps_cpp returned no DataWriter";
        if (writer == nullptr || !write_serialized_w_timestamp(
          writer, view.data(), view.size(), source_timestamp, &why))
        {
          error->set(DdsError, "publish with source_timestamp failed: " + why);
        }
        return;
      }
      // rmw only reads the buffer: point it at the caller's memory, no copy here.
      rmw_serialized_message_t msg = rmw_get_zero_initialized_serialized_message();
      msg.buffer = static_cast<uint8_t *>(view.data());
      msg.buffer_length = view.size();
      msg.buffer_capacity = view.size();
      msg.allocator = rcutils_get_default_allocator();
      if (rmw_publish_serialized_message(publisher, &msg, nullptr) != RMW_RET_OK) {
        set_rmw_error(error, "rmw_publish_serialized_message failed");
      }
    }))
  {
    return nullptr;
  }
  Py_RETURN_NONE;
}

PyObject * pub_matched_gids(PyObject * op, PyObject *)
{
  std::vector<GidArray> gids;
  if (!channel_call(reinterpret_cast<ChannelPublisherObject *>(op),
    [&](rmw_publisher_t * publisher, PendingError * error) {
      std::string why;
      if (!matched_reader_gids(publisher, &gids, &why)) {
        error->set(DdsError, "matched_gids: " + why);
      }
    }))
  {
    return nullptr;
  }
  return gid_list(gids);
}

PyObject * pub_matched_count(PyObject * op, PyObject *)
{
  return matched_count<ChannelPublisherObject>(
    op, rmw_publisher_count_matched_subscriptions, "rmw_publisher_count_matched_subscriptions");
}

/// Block until every matched subscription acknowledged every sample, or `timeout_sec` passes.
PyObject * pub_wait_for_all_acked(PyObject * op, PyObject * arg)
{
  auto * self = reinterpret_cast<ChannelPublisherObject *>(op);
  double timeout_sec = PyFloat_AsDouble(arg);
  if (timeout_sec == -1.0 && PyErr_Occurred()) {
    return nullptr;
  }
  rmw_time_t timeout = RMW_DURATION_INFINITE;
  if (timeout_sec >= 0.0) {
    timeout.sec = static_cast<uint64_t>(timeout_sec);
    timeout.nsec = static_cast<uint64_t>((timeout_sec - static_cast<double>(timeout.sec)) * 1e9);
  }
  bool acked = true;
  if (!channel_call(self, [&](rmw_publisher_t * publisher, PendingError * error) {
      const rmw_ret_t ret = rmw_publisher_wait_for_all_acked(publisher, timeout);
      acked = ret == RMW_RET_OK;
      if (ret != RMW_RET_OK && ret != RMW_RET_TIMEOUT) {
        set_rmw_error(error, "rmw_publisher_wait_for_all_acked failed");
      }
    }))
  {
    return nullptr;
  }
  return PyBool_FromLong(acked);
}

PyMethodDef pub_methods[] = {
  RBPY_METHOD("publish", pub_publish, METH_VARARGS | METH_KEYWORDS,
    "publish(data, source_timestamp=None) -> None\n\nWrite serialized CDR (with its 4-byte "
    "encapsulation header) from any C-contiguous buffer, without copying it in Python; the GIL "
    "is released meanwhile. source_timestamp (int, ns since the epoch) becomes the samples'\n"
    "source timestamp; None lets rmw stamp it with the current time."),
  RBPY_METHOD("matched_count", pub_matched_count, METH_NOARGS,
    "matched_count() -> int: subscriptions currently matched."),
  RBPY_METHOD("matched_gids", pub_matched_gids, METH_NOARGS,
    "matched_gids() -> list[bytes]: 16-byte GIDs of the DataReaders currently matched."),
  RBPY_METHOD("wait_for_all_acked", pub_wait_for_all_acked, METH_O,
    "wait_for_all_acked(timeout_sec: float) -> bool: wait until every matched subscription\n"
    "acknowledged every sample (reliable channels); a negative timeout waits forever."),
  RBPY_METHOD("destroy", channel_destroy<ChannelPublisherObject>, METH_NOARGS,
    "destroy() -> None: delete the rmw publisher and unpin the node (idempotent)."),
  RBPY_METHODS_END,
};

PyGetSetDef pub_getset[] = {
  RBPY_CHANNEL_GETSET(ChannelPublisherObject, "16-byte GID (as in get_publishers_info_by_topic)"),
  {nullptr, nullptr, nullptr, nullptr, nullptr},
};

RBPY_CHANNEL_TYPE(
  pub, ChannelPublisherObject, "ChannelPublisher",
  "ChannelPublisher(node, type_support, topic_name, reliability=1, history=1, depth=10)\n"
  "--\n\n"
  "An rmw_fastrtps publisher below rcl on the node's participant: topic_name is the full\n"
  "DDS name (e.g. 'rt/camera/image/_buf/<hex>_<hex>'), volatile durability. node is an\n"
  "rclpy Node (or its handle, or an rcl_node_t* int); type_support is msg_type._TYPE_SUPPORT.");

// ------------------------------------------------------------------ ChannelSubscription

int sub_init(PyObject * op, PyObject * args, PyObject * kwds)
{
  auto * self = reinterpret_cast<ChannelSubscriptionObject *>(op);
  PyObject * gc_arg = Py_None;
  const rosidl_message_type_support_t * ts;
  rmw_qos_profile_t qos;
  if (channel_init_args(&self->base, args, kwds, &gc_arg, &ts, &qos) < 0) {
    return -1;
  }
  self->guard_condition = new PinnedHandle();
  if (gc_arg != Py_None) {
    if (self->guard_condition->acquire(gc_arg, "guard_condition") < 0) {
      base_unsetup(&self->base);
      return -1;
    }
    self->notify = new NewMessageNotify(
      static_cast<rcl_guard_condition_t *>(self->guard_condition->get()));
  }
  self->buffer = new rmw_serialized_message_t(rmw_get_zero_initialized_serialized_message());
  rmw_subscription_options_t options = rmw_get_default_subscription_options();
  rmw_subscription_t * subscription;
  rmw_gid_t gid;
  std::memset(&gid, 0, sizeof(gid));
  std::string error;
  bool on_udp = false;
  {
    rcutils_allocator_t allocator = rcutils_get_default_allocator();
    if (rmw_serialized_message_init(self->buffer, 0, &allocator) != RMW_RET_OK) {
      rcutils_reset_error();
    }
    // GIL held on purpose (see create_channel_subscription)
    subscription = create_channel_subscription(
      self->base.rmw_node, ts, self->base.topic_name->c_str(), &qos, &options, &on_udp);
    if (subscription == nullptr) {
      error = take_rmw_error();
    } else if (self->notify != nullptr &&
      rmw_subscription_set_on_new_message_callback(
        subscription, on_new_message, self->notify) != RMW_RET_OK)
    {
      error = "rmw_subscription_set_on_new_message_callback: " + take_rmw_error();
      if (rmw_destroy_subscription(self->base.rmw_node, subscription) != RMW_RET_OK) {
        rcutils_reset_error();
      }
      subscription = nullptr;
    }
  }
  if (subscription == nullptr) {
    delete self->notify;
    self->notify = nullptr;
    self->guard_condition->release();
    base_unsetup(&self->base);
    raise_rmw_error("rmw_create_subscription('" + *self->base.topic_name + "') failed", error);
    return -1;
  }
  // Jazzy's rmw has no rmw_get_gid_for_subscription: the graph reports the DataReader's GUID.
  {
    GilRelease nogil;
    eprosima::fastdds::dds::DataReader * reader = rmw_fastrtps_cpp::get_datareader(subscription);
    if (reader != nullptr) {
      rmw_fastrtps_shared_cpp::copy_from_fastrtps_guid_to_byte_array(
        reader->guid(), self->base.gid);
    }
  }
  self->subscription = subscription;
  self->on_udp = on_udp;
  return 0;
}

int do_destroy(ChannelSubscriptionObject * self)
{
  return destroy_channel(self, [self](rmw_subscription_t * subscription, PendingError * error) {
      // rmw holds its callback mutex while calling us: once this returns, no callback is
      // running or will run.
      if (self->notify != nullptr &&
        rmw_subscription_set_on_new_message_callback(subscription, nullptr, nullptr) != RMW_RET_OK)
      {
        rcutils_reset_error();
      }
      if (rmw_destroy_subscription(self->base.rmw_node, subscription) != RMW_RET_OK) {
        set_rmw_error(error, "rmw_destroy_subscription failed");
      }
      if (self->buffer->buffer != nullptr &&
        rmw_serialized_message_fini(self->buffer) != RMW_RET_OK)
      {
        rcutils_reset_error();
      }
    }, [self] {
      delete self->notify;
      self->notify = nullptr;
      self->guard_condition->release();
    });
}

void free_members(ChannelSubscriptionObject * self)
{
  delete self->notify;
  delete self->guard_condition;
  delete self->buffer;
}

/// How take_described() reads a descriptor message (the arguments of decode_described).
struct DescribedPlan
{
  PyObject * msg_class;
  PyObject * ops;
  Py_ssize_t suffix_size;
  Py_ssize_t max_descriptor;
  PyObject * program;
};

/// take(), take_message() and take_described(): one serialized take; with `support`, the CDR
/// is deserialized into a Python message when it can be (see try_deserialize); with `plan`,
/// the bytes come with their descriptor message decoded, or None.
PyObject * sub_take_impl(
  ChannelSubscriptionObject * self, const MessageSupport * support, Py_ssize_t max_size,
  const DescribedPlan * plan = nullptr)
{
  rmw_ret_t ret = RMW_RET_OK;
  bool valid = true;
  bool taken = false;
  bool deserialized = false;
  rmw_message_info_t info = rmw_get_zero_initialized_message_info();
  std::string error;
  OwnedRosMessage ros_message(support);  // created only for a sample to deserialize
  PyThreadState * ts = PyEval_SaveThread();
  // Held until the bytes are copied out of the reused buffer (taken with the GIL released,
  // so no thread ever holds the GIL while waiting for it).
  std::unique_lock<std::mutex> lock(*self->base.op_mutex);
  if (self->subscription == nullptr) {
    valid = false;
  } else {
    const uint64_t seen = self->notify != nullptr ? self->notify->notified.load() : 0;
    ret = rmw_take_serialized_message_with_info(
      self->subscription, self->buffer, &taken, &info, nullptr);
    if (ret != RMW_RET_OK) {
      error = take_rmw_error();
    } else if (taken && support != nullptr && fits(*self->buffer, max_size)) {
      deserialized = try_deserialize(*support, *self->buffer, &ros_message);
    }
    if (self->notify != nullptr && ret == RMW_RET_OK) {
      self->notify->taken(taken, seen);
    }
  }
  PyEval_RestoreThread(ts);
  PyObject * result = nullptr;
  if (!valid) {
    PyErr_SetString(DdsError, "ChannelSubscription was destroyed");
  } else if (ret != RMW_RET_OK) {
    raise_rmw_error("rmw_take_serialized_message_with_info failed", error);
  } else if (!taken) {
    result = Py_NewRef(Py_None);
  } else if (deserialized) {
    lock.unlock();  // the C message is ours: convert it without holding the channel
    result = taken_tuple(support->to_py(ros_message.get()), info);
  } else if (plan == nullptr) {
    result = taken_tuple(serialized_bytes(*self->buffer), info);
  } else {
    PyObject * raw = serialized_bytes(*self->buffer);
    lock.unlock();  // the bytes are ours: decode them without holding the channel
    if (raw != nullptr) {  // (bytes, gid, info, described | None)
      PyObject * described = decode_described(
        reinterpret_cast<const uint8_t *>(PyBytes_AS_STRING(raw)),
        static_cast<size_t>(PyBytes_GET_SIZE(raw)), plan->msg_class, plan->ops,
        plan->suffix_size, plan->max_descriptor, plan->program);
      result = taken_tuple(raw, info, described ? described : Py_None);
      Py_XDECREF(described);
    }
  }
  if (lock.owns_lock()) {
    lock.unlock();
  }
  return result;
}

PyObject * sub_take(PyObject * op, PyObject *)
{
  return sub_take_impl(reinterpret_cast<ChannelSubscriptionObject *>(op), nullptr, -1);
}

PyObject * sub_take_message(PyObject * op, PyObject * args, PyObject * kwds)
{
  static const char * kwlist[] = {"msg_class", "max_size", nullptr};
  PyObject * msg_class;
  Py_ssize_t max_size = -1;
  if (!PyArg_ParseTupleAndKeywords(
      args, kwds, "O|n:take_message", const_cast<char **>(kwlist), &msg_class, &max_size))
  {
    return nullptr;
  }
  MessageSupport support;
  if (support.load(msg_class) < 0) {
    return nullptr;
  }
  return sub_take_impl(reinterpret_cast<ChannelSubscriptionObject *>(op), &support, max_size);
}

PyObject * sub_take_described(PyObject * op, PyObject * args)
{
  DescribedPlan plan{};
  plan.program = Py_None;
  if (!PyArg_ParseTuple(
      args, "OO!nn|O:take_described", &plan.msg_class, &PyTuple_Type, &plan.ops,
      &plan.suffix_size, &plan.max_descriptor, &plan.program))
  {
    return nullptr;
  }
  return sub_take_impl(reinterpret_cast<ChannelSubscriptionObject *>(op), nullptr, -1, &plan);
}

PyObject * sub_matched_count(PyObject * op, PyObject *)
{
  return matched_count<ChannelSubscriptionObject>(
    op, rmw_subscription_count_matched_publishers, "rmw_subscription_count_matched_publishers");
}

PyObject * sub_on_udp(PyObject * op, void *)
{
  return PyBool_FromLong(reinterpret_cast<ChannelSubscriptionObject *>(op)->on_udp);
}

PyMethodDef sub_methods[] = {
  RBPY_METHOD("take", sub_take, METH_NOARGS,
    "take() -> (bytes, publisher_gid, info) | None\n\nTake one serialized message: CDR "
    "bytes, the writer's 16-byte GID and an rclpy-like message info dict."),
  RBPY_METHOD("take_message", sub_take_message, METH_VARARGS | METH_KEYWORDS,
    "take_message(msg_class, max_size=-1) -> (message | bytes, publisher_gid, info) | None\n\n"
    "Take one message and deserialize it into a msg_class instance, as rclpy's take does; CDR "
    "that does not deserialize (a descriptor payload, malformed data), or is longer than "
    "max_size bytes when max_size >= 0, comes back as bytes instead."),
  RBPY_METHOD("take_described", sub_take_described, METH_VARARGS,
    "take_described(msg_class, prefix_ops, suffix_size, max_descriptor, program=None) -> "
    "(bytes, publisher_gid, info, described) | None\n\nTake one serialized message, as take(), "
    "and decode it where it is a descriptor message (the arguments of codec_fast's "
    "decode_descriptor): described is (message without its payload, backend_type, descriptor "
    "bytes), or None for anything else (CPU bytes, a control message, malformed data: the bytes "
    "say what it is)."),
  RBPY_METHOD("matched_count", sub_matched_count, METH_NOARGS,
    "matched_count() -> int: publishers currently matched."),
  RBPY_METHOD("destroy", channel_destroy<ChannelSubscriptionObject>, METH_NOARGS,
    "destroy() -> None: stop notifications, delete the rmw subscription, unpin the node "
    "and the guard condition (idempotent)."),
  RBPY_METHODS_END,
};

PyObject * sub_pending(PyObject * op, void *)
{
  const NewMessageNotify * notify = reinterpret_cast<ChannelSubscriptionObject *>(op)->notify;
  return PyLong_FromUnsignedLongLong(notify != nullptr ? notify->notified.load() : 1);
}

PyGetSetDef sub_getset[] = {
  {"pending", sub_pending, nullptr,
    "Samples announced to the guard condition and not taken since (1 without a guard "
    "condition): 0 means that every sample left will trigger the guard condition (again), "
    "so the channel need not be taken now", nullptr},
  RBPY_CHANNEL_GETSET(
    ChannelSubscriptionObject, "16-byte GID (as in get_subscriptions_info_by_topic)"),
  {"on_udp", sub_on_udp, nullptr, "True if the DataReader listens on UDP only, not on the "
    "participant's shared memory (the default; see ROSIDL_BUFFER_PY_CHANNEL_TRANSPORT)",
    nullptr},
  {nullptr, nullptr, nullptr, nullptr, nullptr},
};

RBPY_CHANNEL_TYPE(
  sub, ChannelSubscriptionObject, "ChannelSubscription",
  "ChannelSubscription(node, type_support, topic_name, reliability=1, history=1, depth=10,\n"
  "                    guard_condition=None)\n--\n\n"
  "An rmw_fastrtps subscription below rcl; new data triggers guard_condition (an rclpy\n"
  "GuardCondition or its handle, pinned until destroy()).");

/// The ChannelPublisher type (set at registration), to recognise write_message's targets.
PyObject * g_channel_publisher_type = nullptr;

/// One target of write_message: a ChannelPublisher or an rclpy publisher (pinned).
struct WriteTarget
{
  ChannelPublisherObject * channel = nullptr;  // borrowed (the targets sequence holds it)
  std::unique_ptr<PinnedHandle> pin;
  rmw_publisher_t * rmw_publisher = nullptr;   // rclpy publishers only
};

int resolve_target(PyObject * target, WriteTarget * out)
{
  if (PyObject_TypeCheck(target, reinterpret_cast<PyTypeObject *>(g_channel_publisher_type))) {
    out->channel = reinterpret_cast<ChannelPublisherObject *>(target);
    return 0;
  }
  out->pin = std::make_unique<PinnedHandle>();
  out->rmw_publisher = pin_rmw_publisher(target, "target", out->pin.get());
  return out->rmw_publisher ? 0 : -1;
}

PyObject * write_message(PyObject *, PyObject * args, PyObject * kwds)
{
  static const char * kwlist[] = {
    "message", "source_timestamp", "targets", "program", "descriptor", nullptr};
  PyObject * message;
  PyObject * ts_arg;
  PyObject * targets_arg;
  PyObject * program = Py_None;
  PyObject * descriptor_arg = Py_None;
  if (!PyArg_ParseTupleAndKeywords(
      args, kwds, "OOO|OO:write_message", const_cast<char **>(kwlist), &message, &ts_arg,
      &targets_arg, &program, &descriptor_arg))
  {
    return nullptr;
  }
  const char * backend = nullptr;
  Py_ssize_t backend_length = 0;
  const char * descriptor = nullptr;
  Py_ssize_t descriptor_length = 0;
  if (descriptor_arg != Py_None) {
    if (!PyTuple_Check(descriptor_arg) || PyTuple_GET_SIZE(descriptor_arg) != 2 ||
      !PyUnicode_Check(PyTuple_GET_ITEM(descriptor_arg, 0)) ||
      !PyBytes_Check(PyTuple_GET_ITEM(descriptor_arg, 1)))
    {
      PyErr_Format(
        PyExc_TypeError, "write_message: descriptor must be a (backend_type, descriptor bytes) "
        "tuple, got %.200R", descriptor_arg);
      return nullptr;
    }
    backend = PyUnicode_AsUTF8AndSize(PyTuple_GET_ITEM(descriptor_arg, 0), &backend_length);
    if (backend == nullptr) {
      return nullptr;
    }
    descriptor = PyBytes_AS_STRING(PyTuple_GET_ITEM(descriptor_arg, 1));
    descriptor_length = PyBytes_GET_SIZE(PyTuple_GET_ITEM(descriptor_arg, 1));
  }
  int64_t source_timestamp;
  if (parse_source_timestamp(ts_arg, &source_timestamp) < 0) {
    return nullptr;
  }
  PyObject * targets = PySequence_Fast(targets_arg, "targets must be a sequence");
  if (targets == nullptr) {
    return nullptr;
  }
  const Py_ssize_t count = PySequence_Fast_GET_SIZE(targets);
  std::vector<WriteTarget> resolved(static_cast<size_t>(count));
  for (Py_ssize_t i = 0; i < count; ++i) {
    if (resolve_target(PySequence_Fast_GET_ITEM(targets, i), &resolved[i]) < 0) {
      Py_DECREF(targets);
      return nullptr;
    }
    if (descriptor != nullptr && resolved[i].channel == nullptr) {
      PyErr_Format(
        PyExc_TypeError, "write_message: target %zd is not a ChannelPublisher: a descriptor "
        "message goes to channels only", i);
      Py_DECREF(targets);
      return nullptr;
    }
  }
  MessageSupport support;
  PyObject * msg_class = reinterpret_cast<PyObject *>(Py_TYPE(message));
  // One conversion for every target: the CDR written from the slots where the type's slot
  // program writes it exactly (no Python getter per field), else the C struct rmw serializes.
  std::vector<char> cdr;
  if (descriptor != nullptr) {
    // only from the slots: the type support has no descriptor form (the caller's codec does).
    // Written to the channels as their publish() writes serialized data: no type support
    // needed (the program is the message's type's, and the channels the caller's for it).
    if (!write_described_from_slots(
        message, program, backend, backend_length, descriptor, descriptor_length, &cdr))
    {
      Py_DECREF(targets);
      Py_RETURN_FALSE;
    }
  } else if (support.load(msg_class) < 0) {
    Py_DECREF(targets);
    return nullptr;
  }
  const bool by_program = descriptor != nullptr || write_from_slots(message, program, &cdr);
  OwnedRosMessage ros_message(&support);
  if (!by_program && ros_message.create() == nullptr) {
    Py_DECREF(targets);
    return PyErr_NoMemory();
  }
  if (!by_program && !support.from_py(message, ros_message.get())) {
    Py_DECREF(targets);
    return nullptr;
  }
  std::string error;
  Py_ssize_t failed = -1;
  bool type_mismatch = false;
  bool destroyed = false;
  {
    GilRelease nogil;
    for (Py_ssize_t i = 0; i < count && failed < 0; ++i) {
      WriteTarget & target = resolved[i];
      std::unique_lock<std::mutex> lock;
      rmw_publisher_t * rmw_pub = target.rmw_publisher;
      if (target.channel != nullptr) {
        lock = std::unique_lock<std::mutex>(*target.channel->base.op_mutex);
        rmw_pub = target.channel->publisher;
        if (rmw_pub == nullptr) {
          destroyed = true;
          failed = i;
          break;
        }
      }
      if (descriptor != nullptr) {
        eprosima::fastdds::dds::DataWriter * writer = rmw_fastrtps_cpp::get_datawriter(rmw_pub);
        error = "rmw_fastrtps_cpp returned no DataWriter";
        if (writer == nullptr || !write_serialized_w_timestamp(
            writer, cdr.data(), cdr.size(), source_timestamp, &error))
        {
          failed = i;
        }
        continue;
      }
      const bool written = by_program ?
        write_cdr_w_timestamp(
        rmw_pub, cdr.data(), cdr.size(), support.callbacks, source_timestamp, &type_mismatch,
        &error) :
        write_message_w_timestamp(
        rmw_pub, ros_message.get(), support.callbacks, source_timestamp, &type_mismatch, &error);
      if (!written) {
        failed = i;
      } else if (target.channel == nullptr) {  // the main topic's writer
        gap_to_excluded_readers(rmw_fastrtps_cpp::get_datawriter(rmw_pub));
      }
    }
  }
  if (failed >= 0) {
    PyObject * target = PySequence_Fast_GET_ITEM(targets, failed);
    if (destroyed) {
      PyErr_Format(DdsError, "write_message: target %zd (%R) was destroyed", failed, target);
    } else if (type_mismatch) {
      PyErr_Format(
        PyExc_TypeError, "write_message: target %zd (%R) does not publish %.200R", failed,
        target, msg_class);
    } else {
      PyErr_Format(DdsError, "write_message: target %zd: %s", failed, error.c_str());
    }
    Py_DECREF(targets);
    return nullptr;
  }
  Py_DECREF(targets);
  Py_RETURN_TRUE;
}

}  // namespace

PyMethodDef channel_functions[] = {
  RBPY_FUNCTION(write_message, METH_VARARGS | METH_KEYWORDS,
    "write_message(message, source_timestamp, targets, program=None, descriptor=None) -> bool"
    "\n\nConvert a ROS message once and write it, with source_timestamp (int, ns since the "
    "epoch), to every target in order: ChannelPublisher objects and rclpy publishers of the "
    "message's type. Converted to its CDR from its slots by `program` (a slot program of "
    "codec/plans.py) where it writes it exactly, else to its C struct (as rclpy's publish does), "
    "which rmw serializes into each DDS payload; the GIL is released for the writes. Stops at "
    "the first failing target. With `descriptor` = (backend_type, descriptor bytes), the "
    "descriptor form (codec.encode(message, descriptor)'s bytes) goes to ChannelPublisher "
    "targets; it is written from the slots only: False, nothing written, when the program "
    "cannot. True once written."),
  RBPY_METHODS_END,
};

int add_channel_types(PyObject * module)
{
  // kept for good: write_message recognises its ChannelPublisher targets by it
  g_channel_publisher_type = Py_XNewRef(rbpy_glue::add_type(module, &pub_spec));
  return g_channel_publisher_type && rbpy_glue::add_type(module, &sub_spec) ? 0 : -1;
}

}  // namespace rbpy_dds
