// Endpoint discovery tap on the DomainParticipant behind an rcl node.
//
//   install_discovery(node) -> bool              (True when this call installed the tap)
//   uninstall_discovery(node) -> bool            (restore rmw's listener; rarely needed)
//   drain_discovery_events(node) -> list[event]
//   list_known_endpoints(node) -> list[event]    (status 'known': alive endpoints seen so far)
//   add_discovery_wakeup(node, guard_condition) -> bool
//   remove_discovery_wakeup(guard_condition) -> bool
//   discovery_stats(node) -> dict
//   silence_discovery(node) -> bool              (the participant stops listening: shutdown)
//   silence_discovery_if_last_node(node) -> bool (the same, when node is its context's last)
//
// event = (kind 'writer'|'reader', status 'discovered'|'changed'|'removed'|'ignored'|'known',
//          gid: bytes[16], topic: str (DDS name, 'rt/...'), type_name: str, user_data: bytes,
//          participant_gid: bytes[16], local: bool (same participant as `node`))
//
// Design (see README.md): one DiscoveryTap per DomainParticipant replaces rmw_fastrtps's
// ParticipantListener (the swap itself is in rmw_fastrtps_private.cpp, behind the version
// guard) and forwards every callback to it first (the ROS graph keeps working),
// then records the event in a mutex-protected queue and triggers the registered rcl guard
// conditions. DDS threads never touch Python. A tap is never deleted: rmw's
// destroy_participant() sets the participant's listener to nullptr before deleting anything,
// so after that the tap is simply unreachable (a few hundred bytes leaked per participant).
// Guard conditions are pinned (their rclpy handle is entered) while registered.
#include <array>
#include <atomic>
#include <cstring>
#include <deque>
#include <map>
#include <mutex>
#include <set>
#include <string>
#include <utility>
#include <vector>

#include "dds_common.hpp"
#include "rmw_fastrtps_private.hpp"

#include "fastdds/dds/domain/DomainParticipant.hpp"
#include "fastdds/dds/domain/DomainParticipantListener.hpp"
#include "fastdds/rtps/participant/ParticipantDiscoveryInfo.h"
#include "fastdds/rtps/reader/ReaderDiscoveryInfo.h"
#include "fastdds/rtps/writer/WriterDiscoveryInfo.h"
#include "rcl/error_handling.h"
#include "rcl/guard_condition.h"
#include "rcl/node.h"
#include "rmw_fastrtps_cpp/get_participant.hpp"
#include "rmw_fastrtps_shared_cpp/guid_utils.hpp"

namespace rbpy_dds
{
namespace
{

namespace dds = eprosima::fastdds::dds;
namespace rtps = eprosima::fastrtps::rtps;

using Gid = std::array<uint8_t, RMW_GID_STORAGE_SIZE>;

constexpr size_t kMaxQueuedEvents = 100000;

/// Discovery callbacks (participants, readers, writers, local ones included) that the taps of
/// this process passed on to rmw: a publisher reads it (through discovery_epoch()) to know
/// when a matched count may have changed, instead of asking DDS on every message. Static, so
/// a view of it stays valid for the life of the process.
alignas(8) std::atomic<uint64_t> g_discovery_epoch{0};
static_assert(std::atomic<uint64_t>::is_always_lock_free, "the epoch is read as plain memory");
static_assert(sizeof(std::atomic<uint64_t>) == sizeof(uint64_t), "the epoch is 8 bytes");

void bump_epoch() {g_discovery_epoch.fetch_add(1, std::memory_order_release);}

Gid to_gid(const rtps::GUID_t & guid)
{
  Gid gid{};
  rmw_fastrtps_shared_cpp::copy_from_fastrtps_guid_to_byte_array(guid, gid.data());
  return gid;
}

Gid participant_gid_of(const rtps::GuidPrefix_t & prefix)
{
  return to_gid(rtps::GUID_t(prefix, rtps::c_EntityId_RTPSParticipant));
}

struct EndpointEvent
{
  bool is_writer = false;
  const char * status = "";
  Gid gid{};
  std::string topic;
  std::string type_name;
  std::vector<uint8_t> user_data;
  Gid participant_gid{};
  bool local = false;
};

struct Wakeup
{
  rcl_guard_condition_t * guard_condition;
  PinnedHandle * pin;  // owned; created and destroyed with the GIL held
};

class DiscoveryTap final : public dds::DomainParticipantListener
{
public:
  DiscoveryTap(dds::DomainParticipant * participant, dds::DomainParticipantListener * original)
  : participant_(participant), original_(original),
    own_prefix_(participant->guid().guidPrefix)
  {}

  dds::DomainParticipant * participant() const {return participant_;}
  dds::DomainParticipantListener * original() const {return original_;}

  // ---- discovery: forward to rmw first, then record ----
  void on_participant_discovery(
    dds::DomainParticipant * p, rtps::ParticipantDiscoveryInfo && info,
    bool & should_be_ignored) override
  {
    const auto status = info.status;
    const rtps::GuidPrefix_t prefix = info.info.m_guid.guidPrefix;
    should_be_ignored = false;
    if (original_) {
      original_->on_participant_discovery(p, std::move(info), should_be_ignored);
    }
    bump_epoch();
    if (status == rtps::ParticipantDiscoveryInfo::REMOVED_PARTICIPANT ||
      status == rtps::ParticipantDiscoveryInfo::DROPPED_PARTICIPANT ||
      status == rtps::ParticipantDiscoveryInfo::IGNORED_PARTICIPANT)
    {
      forget_participant(participant_gid_of(prefix));
    }
  }

  void on_subscriber_discovery(
    dds::DomainParticipant * p, rtps::ReaderDiscoveryInfo && info) override
  {
    observe(false, reader_status(info.status), info.info, [&] {
        original_->on_subscriber_discovery(p, std::move(info));
      });
  }

  void on_publisher_discovery(
    dds::DomainParticipant * p, rtps::WriterDiscoveryInfo && info) override
  {
    observe(true, writer_status(info.status), info.info, [&] {
        original_->on_publisher_discovery(p, std::move(info));
      });
  }

// A callback of the listener interface that only forwards to rmw's listener.
#define RBPY_FORWARD(callback, params, args) \
  void callback params override {if (original_) {original_->callback args;}}

  // ---- everything else: plain forwarding (rmw masks these today) ----
  RBPY_FORWARD(
    on_participant_discovery,
    (dds::DomainParticipant * p, rtps::ParticipantDiscoveryInfo && info), (p, std::move(info)))
  RBPY_FORWARD(
    on_subscriber_discovery,
    (dds::DomainParticipant * p, rtps::ReaderDiscoveryInfo && info, bool & should_be_ignored),
    (p, std::move(info), should_be_ignored))
  RBPY_FORWARD(
    on_publisher_discovery,
    (dds::DomainParticipant * p, rtps::WriterDiscoveryInfo && info, bool & should_be_ignored),
    (p, std::move(info), should_be_ignored))
  RBPY_FORWARD(
    on_type_discovery,
    (dds::DomainParticipant * p, const rtps::SampleIdentity & request_sample_id,
    const eprosima::fastrtps::string_255 & topic,
    const eprosima::fastrtps::types::TypeIdentifier * identifier,
    const eprosima::fastrtps::types::TypeObject * object,
    eprosima::fastrtps::types::DynamicType_ptr dyn_type),
    (p, request_sample_id, topic, identifier, object, dyn_type))
  RBPY_FORWARD(
    on_type_dependencies_reply,
    (dds::DomainParticipant * p, const rtps::SampleIdentity & request_sample_id,
    const eprosima::fastrtps::types::TypeIdentifierWithSizeSeq & dependencies),
    (p, request_sample_id, dependencies))
  RBPY_FORWARD(
    on_type_information_received,
    (dds::DomainParticipant * p, const eprosima::fastrtps::string_255 topic_name,
    const eprosima::fastrtps::string_255 type_name,
    const eprosima::fastrtps::types::TypeInformation & type_information),
    (p, topic_name, type_name, type_information))
  RBPY_FORWARD(
    on_publication_matched, (dds::DataWriter * w, const dds::PublicationMatchedStatus & s),
    (w, s))
  RBPY_FORWARD(
    on_offered_deadline_missed, (dds::DataWriter * w, const dds::OfferedDeadlineMissedStatus & s),
    (w, s))
  RBPY_FORWARD(
    on_offered_incompatible_qos,
    (dds::DataWriter * w, const dds::OfferedIncompatibleQosStatus & s), (w, s))
  RBPY_FORWARD(
    on_liveliness_lost, (dds::DataWriter * w, const dds::LivelinessLostStatus & s), (w, s))
  RBPY_FORWARD(
    on_unacknowledged_sample_removed,
    (dds::DataWriter * w, const dds::InstanceHandle_t & instance), (w, instance))
  RBPY_FORWARD(on_data_on_readers, (dds::Subscriber * sub), (sub))
  RBPY_FORWARD(on_data_available, (dds::DataReader * r), (r))
  RBPY_FORWARD(
    on_subscription_matched, (dds::DataReader * r, const dds::SubscriptionMatchedStatus & s),
    (r, s))
  RBPY_FORWARD(
    on_requested_deadline_missed,
    (dds::DataReader * r, const eprosima::fastrtps::RequestedDeadlineMissedStatus & s), (r, s))
  RBPY_FORWARD(
    on_liveliness_changed,
    (dds::DataReader * r, const eprosima::fastrtps::LivelinessChangedStatus & s), (r, s))
  RBPY_FORWARD(
    on_sample_rejected,
    (dds::DataReader * r, const eprosima::fastrtps::SampleRejectedStatus & s), (r, s))
  RBPY_FORWARD(
    on_requested_incompatible_qos,
    (dds::DataReader * r, const dds::RequestedIncompatibleQosStatus & s), (r, s))
  RBPY_FORWARD(on_sample_lost, (dds::DataReader * r, const dds::SampleLostStatus & s), (r, s))
  RBPY_FORWARD(on_inconsistent_topic, (dds::Topic * t, dds::InconsistentTopicStatus s), (t, s))
#undef RBPY_FORWARD

  // ---- Python-facing (called with the GIL released unless noted) ----
  std::vector<EndpointEvent> drain()
  {
    std::lock_guard<std::mutex> lock(mutex_);
    std::vector<EndpointEvent> out(
      std::make_move_iterator(events_.begin()), std::make_move_iterator(events_.end()));
    events_.clear();
    return out;
  }

  std::vector<EndpointEvent> known()
  {
    std::lock_guard<std::mutex> lock(mutex_);
    std::vector<EndpointEvent> out;
    out.reserve(known_.size());
    for (const auto & kv : known_) {
      out.push_back(kv.second);
      out.back().status = "known";
    }
    return out;
  }

  bool add_wakeup(const Wakeup & w)
  {
    std::lock_guard<std::mutex> lock(mutex_);
    for (const auto & existing : wakeups_) {
      if (existing.guard_condition == w.guard_condition) {
        return false;
      }
    }
    wakeups_.push_back(w);
    return true;
  }

  /// Remove the wakeup of `gc`; returns its pin (to be released with the GIL) or nullptr.
  /// After this returns, `gc` is never triggered by this tap again.
  PinnedHandle * remove_wakeup(const rcl_guard_condition_t * gc)
  {
    std::lock_guard<std::mutex> lock(mutex_);
    for (auto it = wakeups_.begin(); it != wakeups_.end(); ++it) {
      if (it->guard_condition == gc) {
        PinnedHandle * pin = it->pin;
        wakeups_.erase(it);
        return pin;
      }
    }
    return nullptr;
  }

  /// Stop recording and hand back every pin (for a tap that is no longer installed).
  std::vector<PinnedHandle *> detach()
  {
    std::lock_guard<std::mutex> lock(mutex_);
    detached_ = true;
    std::vector<PinnedHandle *> pins;
    for (const auto & w : wakeups_) {
      pins.push_back(w.pin);
    }
    wakeups_.clear();
    events_.clear();
    known_.clear();
    return pins;
  }

  void stats(size_t * queued, size_t * known, size_t * wakeups, uint64_t * dropped,
    uint64_t * recorded)
  {
    std::lock_guard<std::mutex> lock(mutex_);
    *queued = events_.size();
    *known = known_.size();
    *wakeups = wakeups_.size();
    *dropped = dropped_;
    *recorded = recorded_;
  }

private:
  static const char * writer_status(rtps::WriterDiscoveryInfo::DISCOVERY_STATUS s)
  {
    switch (s) {
      case rtps::WriterDiscoveryInfo::DISCOVERED_WRITER: return "discovered";
      case rtps::WriterDiscoveryInfo::CHANGED_QOS_WRITER: return "changed";
      case rtps::WriterDiscoveryInfo::REMOVED_WRITER: return "removed";
      case rtps::WriterDiscoveryInfo::IGNORED_WRITER: return "ignored";
    }
    return "unknown";
  }

  static const char * reader_status(rtps::ReaderDiscoveryInfo::DISCOVERY_STATUS s)
  {
    switch (s) {
      case rtps::ReaderDiscoveryInfo::DISCOVERED_READER: return "discovered";
      case rtps::ReaderDiscoveryInfo::CHANGED_QOS_READER: return "changed";
      case rtps::ReaderDiscoveryInfo::REMOVED_READER: return "removed";
      case rtps::ReaderDiscoveryInfo::IGNORED_READER: return "ignored";
    }
    return "unknown";
  }

  /// An endpoint callback: the event is made first (rmw's listener takes the info over), then
  /// `forward` hands the info to rmw's listener, then the event is recorded.
  template<typename ProxyData, typename Forward>
  void observe(bool is_writer, const char * status, const ProxyData & data, Forward && forward)
  {
    EndpointEvent ev = make_event(is_writer, status, data);
    if (original_) {
      forward();
    }
    bump_epoch();  // before the pairing that follows this callback: readers allow for that
    record(std::move(ev));
  }

  template<class ProxyData>
  EndpointEvent make_event(bool is_writer, const char * status, const ProxyData & data) const
  {
    EndpointEvent ev;
    ev.is_writer = is_writer;
    ev.status = status;
    ev.gid = to_gid(data.guid());
    ev.topic = data.topicName().to_string();
    ev.type_name = data.typeName().to_string();
    ev.user_data = data.m_qos.m_userData.data_vec();
    ev.participant_gid = participant_gid_of(data.guid().guidPrefix);
    ev.local = data.guid().guidPrefix == own_prefix_;
    return ev;
  }

  void record(EndpointEvent && ev)
  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (detached_) {
      return;
    }
    const bool alive = std::strcmp(ev.status, "discovered") == 0 ||
      std::strcmp(ev.status, "changed") == 0;
    if (alive) {
      known_[ev.gid] = ev;
    } else {
      known_.erase(ev.gid);
    }
    push_locked(std::move(ev));
    trigger_locked();
  }

  void forget_participant(const Gid & participant_gid)
  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (detached_) {
      return;
    }
    bool any = false;
    for (auto it = known_.begin(); it != known_.end(); ) {
      if (it->second.participant_gid == participant_gid) {
        EndpointEvent ev = std::move(it->second);
        ev.status = "removed";
        push_locked(std::move(ev));
        it = known_.erase(it);
        any = true;
      } else {
        ++it;
      }
    }
    if (any) {
      trigger_locked();
    }
  }

  void push_locked(EndpointEvent && ev)
  {
    if (events_.size() >= kMaxQueuedEvents) {
      events_.pop_front();
      ++dropped_;
    }
    events_.push_back(std::move(ev));
    ++recorded_;
  }

  void trigger_locked()
  {
    // rcl_trigger_guard_condition only sets a flag and notifies a condition variable: it
    // never calls back into DDS, so holding mutex_ here is safe, and it makes
    // remove_wakeup() a barrier.
    for (const auto & w : wakeups_) {
      if (rcl_trigger_guard_condition(w.guard_condition) != RCL_RET_OK) {
        rcl_reset_error();
      }
    }
  }

  dds::DomainParticipant * const participant_;
  dds::DomainParticipantListener * const original_;
  const rtps::GuidPrefix_t own_prefix_;

  std::mutex mutex_;
  std::deque<EndpointEvent> events_;
  std::map<Gid, EndpointEvent> known_;
  std::vector<Wakeup> wakeups_;
  bool detached_ = false;
  uint64_t dropped_ = 0;
  uint64_t recorded_ = 0;
};

/// participant -> installed tap. Leaked on purpose (no static destruction order issues).
struct Registry
{
  std::mutex mutex;  // held across set_listener(); DDS callbacks never take it
  std::map<dds::DomainParticipant *, DiscoveryTap *> taps;
  /// Participants that stopped listening (silence_discovery): no tap is installed on them again.
  std::set<dds::DomainParticipant *> silenced;
};

Registry & registry()
{
  static Registry * r = new Registry();
  return *r;
}

/// `f(registry)` with the GIL released, under the registry's lock; returns what it returns.
template<typename F>
auto with_registry(F && f) -> decltype(f(registry()))
{
  GilRelease nogil;
  Registry & reg = registry();
  std::lock_guard<std::mutex> lock(reg.mutex);
  return f(reg);
}

/// Release pins with the GIL held.
void release_pins(std::vector<PinnedHandle *> & pins)
{
  for (PinnedHandle * pin : pins) {
    delete pin;
  }
  pins.clear();
}

/// Pin the node `node_arg` into `pin`; the participant behind it. GIL held; returns nullptr
/// with an exception.
dds::DomainParticipant * participant_of(PyObject * node_arg, PinnedHandle * pin)
{
  rmw_node_t * node = pin_rmw_node(node_arg, pin);
  if (node == nullptr) {
    return nullptr;
  }
  dds::DomainParticipant * participant = rmw_fastrtps_cpp::get_domain_participant(node);
  if (participant == nullptr) {
    PyErr_SetString(DdsError, "rmw_fastrtps_cpp returned no DomainParticipant for this node");
    return nullptr;
  }
  return participant;
}

/// Find (and, if `install`, create) the tap of the node's participant. GIL held.
/// *installed_now tells whether this call installed it. Returns nullptr with an exception,
/// or nullptr without one when !install and there is no tap.
DiscoveryTap * tap_of(PyObject * node_arg, bool install, bool * installed_now = nullptr)
{
  PinnedHandle node;
  dds::DomainParticipant * participant = participant_of(node_arg, &node);
  if (participant == nullptr) {
    return nullptr;
  }
  DiscoveryTap * tap = nullptr;
  bool failed = false;
  bool created = false;
  std::string error;
  std::vector<PinnedHandle *> stale_pins;
  with_registry([&](Registry & reg) {
    auto it = reg.taps.find(participant);
    const dds::DomainParticipantListener * current = participant->get_listener();
    if (it != reg.taps.end() && current != it->second) {
      // A participant at a recycled address, or rmw already detached us: forget the old tap.
      stale_pins = it->second->detach();
      reg.taps.erase(it);
      it = reg.taps.end();
    }
    if (reg.silenced.count(participant) != 0) {
      if (current == nullptr) {
        if (install) {
          error = "the participant stopped listening to discovery (its context shut down)";
          failed = true;
        }
        return;
      }
      reg.silenced.erase(participant);  // a new participant at a recycled address
    }
    if (it != reg.taps.end()) {
      tap = it->second;
    } else if (install) {
      auto * original = const_cast<dds::DomainParticipantListener *>(current);
      auto * fresh = new DiscoveryTap(participant, original);
      if (rbpy_dds::rmw_private::set_participant_listener(participant, fresh, &error)) {
        reg.taps[participant] = fresh;
        tap = fresh;
        created = true;
      } else {
        delete fresh;  // never installed, never called
        failed = true;
      }
    }
  });
  release_pins(stale_pins);
  if (failed) {
    PyErr_Format(DdsError, "no discovery tap: %s", error.c_str());
    return nullptr;
  }
  if (installed_now) {
    *installed_now = created;
  }
  return tap;
}

PyObject * event_tuple(const EndpointEvent & ev)
{
  return Py_BuildValue(
    "(ssy#s#s#y#y#O)",
    ev.is_writer ? "writer" : "reader", ev.status,
    reinterpret_cast<const char *>(ev.gid.data()), static_cast<Py_ssize_t>(ev.gid.size()),
    ev.topic.data(), static_cast<Py_ssize_t>(ev.topic.size()),
    ev.type_name.data(), static_cast<Py_ssize_t>(ev.type_name.size()),
    reinterpret_cast<const char *>(ev.user_data.data()),
    static_cast<Py_ssize_t>(ev.user_data.size()),
    reinterpret_cast<const char *>(ev.participant_gid.data()),
    static_cast<Py_ssize_t>(ev.participant_gid.size()),
    ev.local ? Py_True : Py_False);
}

PyObject * event_list(const std::vector<EndpointEvent> & events)
{
  PyObject * list = PyList_New(static_cast<Py_ssize_t>(events.size()));
  if (list == nullptr) {
    return nullptr;
  }
  for (size_t i = 0; i < events.size(); ++i) {
    PyObject * t = event_tuple(events[i]);
    if (t == nullptr) {
      Py_DECREF(list);
      return nullptr;
    }
    PyList_SET_ITEM(list, static_cast<Py_ssize_t>(i), t);
  }
  return list;
}

PyObject * install_discovery(PyObject *, PyObject * node_arg)
{
  bool created = false;
  if (tap_of(node_arg, true, &created) == nullptr) {
    return nullptr;
  }
  return PyBool_FromLong(created);
}

/// `change(reg, participant, &error)` under the registry's lock, for the node's participant;
/// the pins of a tap it detached (with `detach_tap`) are released once the lock is let go.
/// Returns its bool, or raises what it set in `error`.
template<typename F>
PyObject * change_listener(PyObject * node_arg, F && change)
{
  PinnedHandle node;
  dds::DomainParticipant * participant = participant_of(node_arg, &node);
  if (participant == nullptr) {
    return nullptr;
  }
  PendingError error;
  std::vector<PinnedHandle *> pins;
  const bool changed = with_registry([&](Registry & reg) {
    return change(reg, participant, &error, &pins);
  });
  release_pins(pins);
  return error ? error.raise() : PyBool_FromLong(changed);
}

/// Forget the participant's tap, if any: its queue and wakeups go (their pins into `pins`); the
/// tap itself stays allocated, so a late callback is harmless.
void detach_tap(Registry & reg, dds::DomainParticipant * participant,
  std::vector<PinnedHandle *> * pins)
{
  auto it = reg.taps.find(participant);
  if (it != reg.taps.end()) {
    *pins = it->second->detach();
    reg.taps.erase(it);
  }
}

PyObject * uninstall_discovery(PyObject *, PyObject * node_arg)
{
  return change_listener(node_arg, [](Registry & reg, dds::DomainParticipant * participant,
    PendingError * error, std::vector<PinnedHandle *> * pins) {
      auto it = reg.taps.find(participant);
      if (it == reg.taps.end()) {
        return false;
      }
      std::string why;
      if (participant->get_listener() == it->second &&
        !rbpy_dds::rmw_private::set_participant_listener(participant, it->second->original(),
        &why))
      {
        error->set(DdsError, "cannot give rmw its participant listener back: " + why);
        return false;
      }
      detach_tap(reg, participant, pins);
      return true;
    });
}

PyObject * silence_discovery(PyObject *, PyObject * node_arg)
{
  return change_listener(node_arg, [](Registry & reg, dds::DomainParticipant * participant,
    PendingError * error, std::vector<PinnedHandle *> * pins) {
      if (reg.silenced.count(participant) != 0 && participant->get_listener() == nullptr) {
        return false;
      }
      std::string why;
      if (!rbpy_dds::rmw_private::set_participant_listener(participant, nullptr, &why)) {
        error->set(DdsError, "cannot stop the participant's discovery listener: " + why);
        return false;
      }
      detach_tap(reg, participant, pins);
      reg.silenced.insert(participant);
      return true;
    });
}

PyObject * silence_discovery_if_last_node(PyObject *, PyObject * node_arg)
{
  PinnedHandle pin;
  rmw_node_t * node = pin_rmw_node(node_arg, &pin);
  if (node == nullptr) {
    return nullptr;
  }
  std::string why;
  if (!rbpy_dds::rmw_private::only_node_of_context(node, &why)) {
    Py_RETURN_FALSE;  // other nodes share the participant, or rmw's context is not verified
  }
  return silence_discovery(nullptr, node_arg);
}

/// The events `read` returns from the node's tap (installed first; GIL released meanwhile).
PyObject * events_of(PyObject * node_arg, std::vector<EndpointEvent> (DiscoveryTap::* read)())
{
  DiscoveryTap * tap = tap_of(node_arg, true);
  return tap ? event_list(without_gil([&] {return (tap->*read)();})) : nullptr;
}

PyObject * drain_discovery_events(PyObject *, PyObject * node_arg)
{
  return events_of(node_arg, &DiscoveryTap::drain);
}

PyObject * list_known_endpoints(PyObject *, PyObject * node_arg)
{
  return events_of(node_arg, &DiscoveryTap::known);
}

PyObject * add_discovery_wakeup(PyObject *, PyObject * args)
{
  PyObject * node_arg;
  PyObject * gc_arg;
  if (!PyArg_ParseTuple(args, "OO:add_discovery_wakeup", &node_arg, &gc_arg)) {
    return nullptr;
  }
  DiscoveryTap * tap = tap_of(node_arg, true);
  if (tap == nullptr) {
    return nullptr;
  }
  auto * pin = new PinnedHandle();
  if (pin->acquire(gc_arg, "guard_condition") < 0) {
    delete pin;
    return nullptr;
  }
  Wakeup w{static_cast<rcl_guard_condition_t *>(pin->get()), pin};
  bool added;
  {
    GilRelease nogil;
    added = tap->add_wakeup(w);
  }
  if (!added) {
    delete pin;
  }
  return PyBool_FromLong(added);
}

PyObject * remove_discovery_wakeup(PyObject *, PyObject * gc_arg)
{
  // Only peek at the pointer: the guard condition may already be marked for destruction
  // (rclpy deferred it because of our pin), and entering it again would raise.
  void * gc = PinnedHandle::peek(gc_arg, "guard_condition");
  if (gc == nullptr) {
    return nullptr;
  }
  std::vector<PinnedHandle *> pins;
  with_registry([&](Registry & reg) {
    for (auto & kv : reg.taps) {
      if (PinnedHandle * pin = kv.second->remove_wakeup(static_cast<rcl_guard_condition_t *>(gc))) {
        pins.push_back(pin);
      }
    }
  });
  const bool removed = !pins.empty();
  release_pins(pins);
  return PyBool_FromLong(removed);
}

PyObject * discovery_epoch(PyObject *, PyObject *)
{
  return PyMemoryView_FromMemory(
    reinterpret_cast<char *>(&g_discovery_epoch), sizeof(uint64_t), PyBUF_READ);
}

PyObject * discovery_stats(PyObject *, PyObject * node_arg)
{
  DiscoveryTap * tap = tap_of(node_arg, false);
  if (tap == nullptr) {
    if (PyErr_Occurred()) {
      return nullptr;
    }
    return Py_BuildValue("{s:O}", "installed", Py_False);
  }
  size_t queued, known, wakeups;
  uint64_t dropped, recorded;
  {
    GilRelease nogil;
    tap->stats(&queued, &known, &wakeups, &dropped, &recorded);
  }
  return Py_BuildValue(
    "{s:O,s:n,s:n,s:n,s:K,s:K}", "installed", Py_True,
    "queued", static_cast<Py_ssize_t>(queued), "known", static_cast<Py_ssize_t>(known),
    "wakeups", static_cast<Py_ssize_t>(wakeups),
    "dropped", static_cast<unsigned long long>(dropped),
    "recorded", static_cast<unsigned long long>(recorded));
}

}  // namespace

PyMethodDef discovery_functions[] = {
  RBPY_FUNCTION(install_discovery, METH_O,
    "install_discovery(node) -> bool\n\n"
    "Install the discovery tap on the node's DomainParticipant (once per participant; the\n"
    "other discovery functions do it implicitly). True if this call installed it. Install\n"
    "it right after creating the node: endpoints discovered earlier are not replayed."),
  RBPY_FUNCTION(uninstall_discovery, METH_O,
    "uninstall_discovery(node) -> bool\n\n"
    "Give the participant rmw's own listener back and drop queued events and wakeups."),
  RBPY_FUNCTION(drain_discovery_events, METH_O,
    "drain_discovery_events(node) -> list[event]\n\n"
    "Take every queued endpoint event of the node's participant (one consumer per\n"
    "participant). event = (kind, status, gid, topic, type_name, user_data,\n"
    "participant_gid, local)."),
  RBPY_FUNCTION(list_known_endpoints, METH_O,
    "list_known_endpoints(node) -> list[event]\n\n"
    "Snapshot of the endpoints discovered (and not removed) since the tap was installed,\n"
    "with their latest USER_DATA; status 'known'."),
  RBPY_FUNCTION(add_discovery_wakeup, METH_VARARGS,
    "add_discovery_wakeup(node, guard_condition) -> bool\n\n"
    "Trigger this rcl guard condition on every recorded event. The guard condition is\n"
    "pinned (rclpy defers destroying it) until remove_discovery_wakeup()."),
  RBPY_FUNCTION(remove_discovery_wakeup, METH_O,
    "remove_discovery_wakeup(guard_condition) -> bool\n\n"
    "Stop triggering it (on every participant) and unpin it; once this returns it is never\n"
    "triggered again. Works after rclpy was asked to destroy the guard condition."),
  RBPY_FUNCTION(silence_discovery_if_last_node, METH_O,
    "silence_discovery_if_last_node(node) -> bool\n\n"
    "silence_discovery(node) when node is the only node of its context, which rmw destroys\n"
    "the participant with (its unbounded set_listener wait then finds nothing running);\n"
    "False, nothing done, while other nodes share the participant."),
  RBPY_FUNCTION(silence_discovery, METH_O,
    "silence_discovery(node) -> bool\n\n"
    "Stop the node's participant listening to discovery (rmw's graph listener and the tap),\n"
    "waiting for running callbacks in bounded steps; no tap is installed on it again. For a\n"
    "context that shut down or a process that exits: rmw's own unbounded wait when it\n"
    "destroys the participant then has no callback to wait for. True if this call did it."),
  RBPY_FUNCTION(discovery_epoch, METH_NOARGS,
    "discovery_epoch() -> memoryview\n\n"
    "8 read-only bytes, the process's count of discovery callbacks its taps passed to rmw\n"
    "(participants, readers, writers, local ones too), counted after rmw had each: read it\n"
    "with .cast('Q')[0] (an aligned 8-byte load). A matched count changes only after such a\n"
    "callback, shortly after it (Fast DDS pairs the endpoint once the listener returns)."),
  RBPY_FUNCTION(discovery_stats, METH_O,
    "discovery_stats(node) -> dict (installed, queued, known, wakeups, dropped, recorded)"),
  RBPY_METHODS_END,
};

}  // namespace rbpy_dds
