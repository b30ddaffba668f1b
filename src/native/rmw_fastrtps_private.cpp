// Private-layout access to rmw_fastrtps (see rmw_fastrtps_private.hpp). No Python in here.
//
// Mirrors, for the versions in built_versions() (ROS 2 Jazzy: rmw_fastrtps 8.4.x, Fast DDS
// 2.14.x):
// - rmw_fastrtps_shared_cpp/include/rmw_fastrtps_shared_cpp/custom_publisher_info.hpp:
//   CustomPublisherInfo (data_writer_, type_support_impl_, publisher_event_) behind
//   rmw_publisher_t::data, and RMWPublisherEvent's private subscriptions_ (a
//   std::set<GUID_t>) and subscriptions_mutex_, kept by its on_publication_matched;
// - rmw_fastrtps_shared_cpp/src/participant.cpp (__create_participant): rmw installs its own
//   ParticipantListener on the DomainParticipant; we replace it with a tap that forwards every
//   callback to it (dds_discovery.cpp), and give it back on uninstall;
// - Fast DDS src/cpp/fastdds/publisher/DataWriterImpl.hpp (v2.14.0 to v2.14.6, not installed):
//   `class DataWriterImpl : protected rtps::IReaderDataFilter` whose first data members are
//   `PublisherImpl* publisher_` and `RTPSWriter* writer_` (DataWriterImplHead below). Reached
//   from the installed DataWriter.hpp's protected `impl_`; checked against the DataWriter's
//   publisher (Publisher.hpp's protected `impl_`) and GUID before the writer is used;
// - rmw_fastrtps_shared_cpp/include/rmw_fastrtps_shared_cpp/rmw_context_impl.hpp and
//   custom_participant_info.hpp: rmw_context_impl_s::participant_info, a CustomParticipantInfo
//   whose subscriber_ is the one Subscriber rmw creates every DataReader with (read to adjust
//   the default DataReaderQos around a channel subscription's creation, dds_channels.cpp), and
//   publisher_ the one Publisher of every DataWriter; and rmw_context_impl_s::count, the
//   context's node count, under its mutex: rmw_fastrtps_shared_cpp/src/
//   init_rmw_context_impl.cpp destroys the participant when it drops to 0
//   (only_node_of_context);
// - Fast DDS's installed Entity.hpp: the protected `enable_` flag of a Publisher or Subscriber,
//   which PublisherImpl::create_datawriter and SubscriberImpl::create_datareader read (with
//   autoenable_created_entities) to enable what they create, and which only set_qos reads
//   besides (src/cpp/fastdds/{publisher,subscriber}/*Impl.cpp, v2.14.6); cleared around a
//   buffer-aware endpoint's creation (hold_enabling);
// - Fast DDS's installed RTPSWriter.h: its protected `mp_history` (the WriterHistory, whose
//   public next_sequence_number() tells the next sample's sequence number).
// The layouts come from the headers of the prefix setup.py builds against. A patch release that
// changes them would make these reads wrong without any error, hence the version guard: nothing
// here runs until rosidl_buffer_py._dds found the running libraries to be the built versions.
#include "rmw_fastrtps_private.hpp"

#include <atomic>
#include <chrono>
#include <mutex>
#include <set>
#include <string>

#include "fastdds/dds/core/Entity.hpp"
#include "fastdds/dds/domain/DomainParticipant.hpp"
#include "fastdds/dds/domain/DomainParticipantListener.hpp"
#include "fastdds/dds/publisher/DataWriter.hpp"
#include "fastdds/dds/publisher/Publisher.hpp"
#include "fastdds/rtps/history/WriterHistory.h"
#include "fastdds/rtps/writer/RTPSWriter.h"
#include "fastrtps/config.h"
#include "fastdds/dds/subscriber/DataReader.hpp"
#include "fastdds/dds/subscriber/Subscriber.hpp"
#include "rmw/init.h"
#include "rmw_fastrtps_cpp/get_participant.hpp"
#include "rmw_fastrtps_shared_cpp/custom_participant_info.hpp"
#include "rmw_fastrtps_shared_cpp/custom_publisher_info.hpp"
#include "rmw_fastrtps_shared_cpp/rmw_context_impl.hpp"

#ifndef RBPY_BUILT_RMW_FASTRTPS_CPP
#define RBPY_BUILT_RMW_FASTRTPS_CPP "unknown"
#endif
#ifndef RBPY_BUILT_RMW_FASTRTPS_SHARED_CPP
#define RBPY_BUILT_RMW_FASTRTPS_SHARED_CPP "unknown"
#endif

namespace rbpy_dds
{
namespace rmw_private
{

namespace
{

std::atomic<bool> g_verified{false};

const char kNotVerified[] =
  "rmw_fastrtps's private layout is not verified for the running libraries (see "
  "rosidl_buffer_py._dds.abi_status())";

// Read access to RMWPublisherEvent's private members: the standard's rule that explicit
// instantiations skip access checks lets us name them.
struct MatchedSetTag
{
  using type = std::set<eprosima::fastrtps::rtps::GUID_t> RMWPublisherEvent::*;
};
struct MatchedMutexTag
{
  using type = std::mutex RMWPublisherEvent::*;
};
MatchedSetTag::type member_of(MatchedSetTag);
MatchedMutexTag::type member_of(MatchedMutexTag);

template<typename Tag, typename Tag::type Member>
struct ExposeMember
{
  friend typename Tag::type member_of(Tag) {return Member;}
};
template struct ExposeMember<MatchedSetTag, &RMWPublisherEvent::subscriptions_>;
template struct ExposeMember<MatchedMutexTag, &RMWPublisherEvent::subscriptions_mutex_>;

struct WriterImplTag
{
  using type = eprosima::fastdds::dds::DataWriterImpl * eprosima::fastdds::dds::DataWriter::*;
};
struct PublisherImplTag
{
  using type = eprosima::fastdds::dds::PublisherImpl * eprosima::fastdds::dds::Publisher::*;
};
struct WriterHistoryTag
{
  using type =
    eprosima::fastrtps::rtps::WriterHistory * eprosima::fastrtps::rtps::RTPSWriter::*;
};
WriterImplTag::type member_of(WriterImplTag);
PublisherImplTag::type member_of(PublisherImplTag);
WriterHistoryTag::type member_of(WriterHistoryTag);
template struct ExposeMember<WriterImplTag, &eprosima::fastdds::dds::DataWriter::impl_>;
template struct ExposeMember<PublisherImplTag, &eprosima::fastdds::dds::Publisher::impl_>;
template struct ExposeMember<WriterHistoryTag, &eprosima::fastrtps::rtps::RTPSWriter::mp_history>;

/// The start of Fast DDS 2.14's DataWriterImpl (see the top of this file).
struct DataWriterImplHead
{
  const void * vtable;  // of its only base, IReaderDataFilter (so at offset 0)
  const void * publisher;  // PublisherImpl*
  eprosima::fastrtps::rtps::RTPSWriter * writer;
};

}  // namespace

const std::vector<BuiltVersion> & built_versions()
{
  static const std::vector<BuiltVersion> versions = {
    {"rmw_fastrtps_cpp", RBPY_BUILT_RMW_FASTRTPS_CPP},
    {"rmw_fastrtps_shared_cpp", RBPY_BUILT_RMW_FASTRTPS_SHARED_CPP},
    {"fastrtps", FASTRTPS_VERSION_STR},
  };
  return versions;
}

bool layout_verified()
{
  return g_verified.load();
}

void set_layout_verified(bool verified)
{
  g_verified.store(verified);
}

bool publisher_parts(rmw_publisher_t * publisher, PublisherParts * parts, std::string * error)
{
  if (!layout_verified()) {
    *error = kNotVerified;
    return false;
  }
  auto * info = static_cast<CustomPublisherInfo *>(publisher->data);
  if (info == nullptr || info->data_writer_ == nullptr) {
    *error = "the publisher has no DataWriter";
    return false;
  }
  parts->writer = info->data_writer_;
  parts->type_support_impl = info->type_support_impl_;
  return true;
}

bool rmw_matched_readers(
  rmw_publisher_t * publisher, std::vector<eprosima::fastrtps::rtps::GUID_t> * guids,
  std::string * error)
{
  if (!layout_verified()) {
    *error = kNotVerified;
    return false;
  }
  auto * info = static_cast<CustomPublisherInfo *>(publisher->data);
  if (info == nullptr || info->publisher_event_ == nullptr) {
    *error = "the rmw publisher has no publisher event";
    return false;
  }
  // The mutex is taken only by rmw's on_publication_matched, briefly and without calling out.
  RMWPublisherEvent * event = info->publisher_event_;
  std::lock_guard<std::mutex> lock(event->*member_of(MatchedMutexTag{}));
  const auto & matched = event->*member_of(MatchedSetTag{});
  guids->assign(matched.begin(), matched.end());
  return true;
}

// DomainParticipantImpl::set_listener (v2.14.6, DomainParticipantImpl.hpp) waits for running
// discovery callbacks with condition_variable::wait_until on a steady_clock deadline, "forever"
// (time_point::max()) by default. The PyPI build of Fast DDS links against a glibc without
// pthread_cond_clockwait, so libstdc++ converts that deadline to system_clock, where max()
// overflows into the past: the wait returns at once, finds its deadline not reached, and loops,
// re-taking mtx_gs_, which the running callback needs to finish (its Sentry's destructor). On a
// busy machine that livelock lasted as long as we watched (a process hung installing the tap,
// or in rmw's destroy_participant at exit). A bounded deadline converts correctly and waits.
constexpr int kListenerWaitSeconds = 1;
constexpr int kListenerWaitAttempts = 30;

bool set_participant_listener(
  eprosima::fastdds::dds::DomainParticipant * participant,
  eprosima::fastdds::dds::DomainParticipantListener * listener, std::string * error)
{
  if (!layout_verified()) {
    *error = kNotVerified;
    return false;
  }
  // Not under any lock a callback takes: set_listener waits for running callbacks, here always
  // with a bounded wait (see kListenerWaitSeconds), repeated while callbacks keep running.
  const eprosima::fastdds::dds::StatusMask mask = participant->get_status_mask();
  for (int attempt = 0; attempt < kListenerWaitAttempts; ++attempt) {
    if (participant->set_listener(listener, mask, std::chrono::seconds(kListenerWaitSeconds)) ==
      eprosima::fastrtps::types::ReturnCode_t::RETCODE_OK)
    {
      return true;
    }
  }
  *error = "DomainParticipant::set_listener: discovery callbacks kept running for " +
    std::to_string(kListenerWaitAttempts * kListenerWaitSeconds) + " s";
  return false;
}

eprosima::fastrtps::rtps::RTPSWriter * rtps_writer_of(
  eprosima::fastdds::dds::DataWriter * writer, std::string * error)
{
  if (!layout_verified()) {
    *error = kNotVerified;
    return nullptr;
  }
  const void * impl = writer->*member_of(WriterImplTag{});
  const eprosima::fastdds::dds::Publisher * publisher = writer->get_publisher();
  if (impl == nullptr || publisher == nullptr) {
    *error = "the DataWriter has no implementation or no publisher";
    return nullptr;
  }
  const auto * head = static_cast<const DataWriterImplHead *>(impl);
  // The publisher pointer is checked before the writer pointer is followed.
  if (head->publisher != static_cast<const void *>(publisher->*member_of(PublisherImplTag{})) ||
    head->writer == nullptr || head->writer->getGuid() != writer->guid())
  {
    *error = "Fast DDS's DataWriterImpl does not have the layout of 2.14";
    return nullptr;
  }
  return head->writer;
}

bool is_own_reader_filter(eprosima::fastdds::dds::DataWriter * writer, const void * filter)
{
  return layout_verified() && filter != nullptr &&
         filter == static_cast<const void *>(writer->*member_of(WriterImplTag{}));
}

int64_t next_sequence_number(eprosima::fastrtps::rtps::RTPSWriter * writer)
{
  eprosima::fastrtps::rtps::WriterHistory * history = writer->*member_of(WriterHistoryTag{});
  return history == nullptr ? -1 : history->next_sequence_number().to64long();
}

namespace
{

/// rmw's participant info of the node, checked to be that of the node's participant.
CustomParticipantInfo * participant_info_of(rmw_node_t * node, std::string * error)
{
  if (!layout_verified()) {
    *error = kNotVerified;
    return nullptr;
  }
  eprosima::fastdds::dds::DomainParticipant * participant =
    rmw_fastrtps_cpp::get_domain_participant(node);
  if (participant == nullptr || node->context == nullptr || node->context->impl == nullptr ||
    node->context->impl->participant_info == nullptr)
  {
    *error = "the node has no participant";
    return nullptr;
  }
  auto * info = static_cast<CustomParticipantInfo *>(node->context->impl->participant_info);
  // Checked before use: rmw's participant info points to the node's participant, and its
  // Publisher and Subscriber belong to it.
  if (info->participant_ != participant || info->subscriber_ == nullptr ||
    info->subscriber_->get_participant() != participant || info->publisher_ == nullptr ||
    info->publisher_->get_participant() != participant)
  {
    *error = "rmw's participant info does not have the layout of rmw_fastrtps 8.4";
    return nullptr;
  }
  return info;
}

/// Entity's protected `enable_`, reached as a pointer to member through a subclass (the
/// language's own access to a protected member; nothing of the layout is assumed).
struct EnabledFlag : eprosima::fastdds::dds::Entity
{
  static bool eprosima::fastdds::dds::Entity::* member() {return &EnabledFlag::enable_;}
};

template<typename Group, typename Endpoint>
bool let_go(Group * group, std::vector<Endpoint *> & endpoints, std::string * error)
{
  group->*EnabledFlag::member() = true;
  bool ok = true;
  for (Endpoint * endpoint : endpoints) {
    if (!endpoint->is_enabled() &&
      endpoint->enable() != eprosima::fastrtps::types::ReturnCode_t::RETCODE_OK)
    {
      *error = "Fast DDS refused to enable an endpoint created while enabling was held";
      ok = false;
    }
  }
  return ok;
}

}  // namespace

eprosima::fastdds::dds::Subscriber * rmw_subscriber_of(rmw_node_t * node, std::string * error)
{
  CustomParticipantInfo * info = participant_info_of(node, error);
  return info == nullptr ? nullptr : info->subscriber_;
}

bool only_node_of_context(rmw_node_t * node, std::string * error)
{
  if (participant_info_of(node, error) == nullptr) {  // verified, and the node's own context
    return false;
  }
  std::lock_guard<std::mutex> lock(node->context->impl->mutex);
  return node->context->impl->count == 1;
}

bool hold_enabling(rmw_node_t * node, bool writers, bool hold, std::string * error)
{
  CustomParticipantInfo * info = participant_info_of(node, error);
  if (info == nullptr) {
    return false;
  }
  if (hold) {
    if (writers) {
      info->publisher_->*EnabledFlag::member() = false;
    } else {
      info->subscriber_->*EnabledFlag::member() = false;
    }
    return true;
  }
  if (writers) {
    std::vector<eprosima::fastdds::dds::DataWriter *> list;
    info->publisher_->get_datawriters(list);
    return let_go(info->publisher_, list, error);
  }
  std::vector<eprosima::fastdds::dds::DataReader *> list;
  info->subscriber_->get_datareaders(list);
  return let_go(info->subscriber_, list, error);
}

}  // namespace rmw_private
}  // namespace rbpy_dds
