// DataWriter helpers (see dds_writer.hpp). No Python in here.
#include "dds_writer.hpp"

#include <algorithm>
#include <deque>
#include <map>
#include <mutex>

#include "fastcdr/Cdr.h"
#include "fastcdr/FastBuffer.h"
#include "fastdds/dds/common/InstanceHandle.hpp"
#include "fastdds/dds/publisher/DataWriter.hpp"
#include "fastdds/rtps/common/InstanceHandle.h"
#include "fastdds/rtps/common/Time_t.h"
#include "fastdds/rtps/interfaces/IReaderDataFilter.hpp"
#include "fastdds/rtps/messages/RTPSMessageGroup.h"
#include "fastdds/rtps/writer/RTPSWriter.h"
#include "fastdds/rtps/writer/ReaderProxy.h"
#include "fastdds/rtps/writer/StatefulWriter.h"
#include "rmw_fastrtps_private.hpp"
#include "rmw_fastrtps_shared_cpp/TypeSupport.hpp"
#include "rmw_fastrtps_shared_cpp/guid_utils.hpp"

namespace rbpy_dds
{

using eprosima::fastrtps::types::ReturnCode_t;

namespace
{

using eprosima::fastrtps::rtps::GUID_t;

GidArray to_gid_array(const GUID_t & guid)
{
  GidArray gid{};
  rmw_fastrtps_shared_cpp::copy_from_fastrtps_guid_to_byte_array(guid, gid.data());
  return gid;
}

/// The reader filter of a main-topic RTPSWriter: which readers a sample (by sequence number)
/// must not reach. Fast DDS asks it, under the writer's mutex, when a sample is added (reliable
/// writers; for each reader) or delivered (best-effort writers; for each fragment), and for the
/// history a late-joining TRANSIENT_LOCAL reader gets. A sample it has no entry for (an old one,
/// or one another thread delivers late) reaches every reader: an extra copy, never a loss.
class ReaderExclusions final : public eprosima::fastdds::rtps::IReaderDataFilter
{
public:
  explicit ReaderExclusions(const eprosima::fastdds::rtps::IReaderDataFilter * previous)
  : previous_(previous) {}

  bool is_relevant(
    const eprosima::fastrtps::rtps::CacheChange_t & change,
    const GUID_t & reader_guid) const override
  {
    const int64_t sequence = change.sequenceNumber.to64long();
    {
      std::lock_guard<std::mutex> lock(mutex_);
      for (auto it = entries_.rbegin(); it != entries_.rend(); ++it) {
        if (it->sequence == sequence) {
          if (std::find(it->readers.begin(), it->readers.end(), reader_guid) !=
            it->readers.end())
          {
            return false;
          }
          break;
        }
      }
    }
    return previous_ == nullptr || previous_->is_relevant(change, reader_guid);
  }

  /// Exclude `readers` from the sample `sequence` (replacing an entry for it).
  void exclude(int64_t sequence, std::vector<GUID_t> readers)
  {
    std::lock_guard<std::mutex> lock(mutex_);
    while (!entries_.empty() && entries_.back().sequence >= sequence) {
      entries_.pop_back();  // registered for a write that did not happen
    }
    if (!readers.empty()) {
      entries_.push_back({sequence, std::move(readers)});
      if (entries_.size() > kKeptEntries) {
        entries_.pop_front();
      }
    }
  }

  const eprosima::fastdds::rtps::IReaderDataFilter * previous() const {return previous_;}

  /// The readers the sample `sequence` was kept from (none when it has no entry).
  std::vector<GUID_t> excluded_from(int64_t sequence) const
  {
    std::lock_guard<std::mutex> lock(mutex_);
    for (auto it = entries_.rbegin(); it != entries_.rend(); ++it) {
      if (it->sequence == sequence) {
        return it->readers;
      }
      if (it->sequence < sequence) {
        break;
      }
    }
    return {};
  }

private:
  /// Samples remembered: far more than are ever in flight between their write and delivery.
  static constexpr size_t kKeptEntries = 256;
  struct Entry
  {
    int64_t sequence;
    std::vector<GUID_t> readers;
  };
  const eprosima::fastdds::rtps::IReaderDataFilter * previous_;
  mutable std::mutex mutex_;
  std::deque<Entry> entries_;
};

/// The filters we installed, by RTPSWriter. An entry whose writer no longer has our filter
/// (rclpy destroyed the publisher without our remove) is stale: dropped, its filter leaked
/// (a writer may still point at it for all we know).
std::mutex g_exclusions_mutex;
std::map<const eprosima::fastrtps::rtps::RTPSWriter *, ReaderExclusions *> g_exclusions;

/// Our filter on `rtps` (g_exclusions_mutex held): the installed one, or nullptr.
ReaderExclusions * installed_exclusions(eprosima::fastrtps::rtps::RTPSWriter * rtps)
{
  auto it = g_exclusions.find(rtps);
  if (it == g_exclusions.end()) {
    return nullptr;
  }
  if (rtps->reader_data_filter() != it->second) {
    g_exclusions.erase(it);
    return nullptr;
  }
  return it->second;
}

/// The RTPSWriter of an rmw_fastrtps_cpp publisher's DataWriter. False with *error when rmw's
/// layout is not verified; true with *rtps null when Fast DDS's does not check out.
/// `f(parts, rtps_writer)` under the exclusion registry's lock, when the publisher's
/// DataWriter has an RTPSWriter we may reach (else nothing happens: true). False with `error`
/// when its parts did not check out.
template<typename F>
bool with_main_rtps_writer(rmw_publisher_t * publisher, std::string * error, F && f)
{
  rmw_private::PublisherParts info;
  if (!rmw_private::publisher_parts(publisher, &info, error)) {
    return false;
  }
  std::string unavailable;
  eprosima::fastrtps::rtps::RTPSWriter * rtps = rmw_private::rtps_writer_of(
    info.writer, &unavailable);
  if (rtps != nullptr) {
    std::lock_guard<std::mutex> registry(g_exclusions_mutex);
    f(info, rtps);
  }
  return true;
}

}  // namespace

bool exclude_from_next_write(
  rmw_publisher_t * publisher, const std::vector<GidArray> & readers, bool * available,
  std::string * error)
{
  *available = false;
  std::vector<GUID_t> guids(readers.size());
  for (size_t i = 0; i < readers.size(); ++i) {
    rmw_fastrtps_shared_cpp::copy_from_byte_array_to_fastrtps_guid(readers[i].data(), &guids[i]);
  }
  return with_main_rtps_writer(publisher, error, [&](
      const rmw_private::PublisherParts & info, eprosima::fastrtps::rtps::RTPSWriter * rtps) {
      ReaderExclusions * exclusions = installed_exclusions(rtps);
      if (exclusions == nullptr) {
        std::lock_guard<eprosima::fastrtps::RecursiveTimedMutex> writer_lock(rtps->getMutex());
        const auto * previous = rtps->reader_data_filter();
        if (previous != nullptr && !rmw_private::is_own_reader_filter(info.writer, previous)) {
          return;  // someone else's filter: leave it alone
        }
        exclusions = new ReaderExclusions(previous);
        rtps->reader_data_filter(exclusions);
        g_exclusions[rtps] = exclusions;
      }
      const int64_t sequence = rmw_private::next_sequence_number(rtps);
      if (sequence > 0) {
        exclusions->exclude(sequence, std::move(guids));
        *available = true;
      }
    });
}

bool remove_write_exclusions(rmw_publisher_t * publisher, std::string * error)
{
  return with_main_rtps_writer(publisher, error, [](
      const rmw_private::PublisherParts &, eprosima::fastrtps::rtps::RTPSWriter * rtps) {
      ReaderExclusions * exclusions = installed_exclusions(rtps);
      if (exclusions == nullptr) {
        return;
      }
      {
        // Fast DDS asks the filter under this mutex only: once it is ours again, nobody uses it.
        std::lock_guard<eprosima::fastrtps::RecursiveTimedMutex> writer_lock(rtps->getMutex());
        rtps->reader_data_filter(
          const_cast<eprosima::fastdds::rtps::IReaderDataFilter *>(exclusions->previous()));
      }
      g_exclusions.erase(rtps);
      delete exclusions;
    });
}

/// After a write on a main-topic writer: a GAP for the sample to each reliable reader it was
/// kept from, as Fast DDS sends a reader a relevant sample at once. Fast DDS itself tells a
/// reader of an irrelevant sample only when the reader asks (its ACKNACK after a HEARTBEAT), and
/// on a KEEP_LAST writer the sample may have left the history by then: a reader whose process
/// was stalled meanwhile gets a HEARTBEAT whose first sample is past it and counts the sample
/// lost, a MESSAGE_LOST event that stock, which sent the sample, never causes. The GAP goes out
/// in order before any later HEARTBEAT, so the reader marks the sample irrelevant first.
void gap_to_excluded_readers(eprosima::fastdds::dds::DataWriter * writer)
{
  std::lock_guard<std::mutex> registry(g_exclusions_mutex);
  if (writer == nullptr || g_exclusions.empty()) {
    return;  // no main-topic writer of this process keeps samples from anyone
  }
  std::string unavailable;
  eprosima::fastrtps::rtps::RTPSWriter * rtps = rmw_private::rtps_writer_of(writer, &unavailable);
  ReaderExclusions * exclusions = rtps == nullptr ? nullptr : installed_exclusions(rtps);
  auto * stateful = dynamic_cast<eprosima::fastrtps::rtps::StatefulWriter *>(rtps);
  if (exclusions == nullptr || stateful == nullptr) {
    return;  // not a writer we filter, or a best-effort one (its readers get no HEARTBEAT)
  }
  std::lock_guard<eprosima::fastrtps::RecursiveTimedMutex> writer_lock(rtps->getMutex());
  const int64_t sequence = rmw_private::next_sequence_number(rtps) - 1;
  std::vector<GUID_t> readers = exclusions->excluded_from(sequence);
  const eprosima::fastrtps::rtps::SequenceNumber_t sample(
    static_cast<int32_t>(sequence >> 32), static_cast<uint32_t>(sequence & 0xffffffffu));
  for (GUID_t & guid : readers) {
    eprosima::fastrtps::rtps::ReaderProxy * proxy = nullptr;
    if (!stateful->matched_reader_lookup(guid, &proxy) || proxy == nullptr ||
      !proxy->is_reliable() || proxy->is_datasharing_reader())
    {
      continue;
    }
    if (proxy->is_local_reader()) {
      stateful->intraprocess_gap(proxy, sample);
      continue;
    }
    try {
      // sent when the group goes out of scope, as StatefulWriter's own personal GAPs are
      eprosima::fastrtps::rtps::RTPSMessageGroup group(
        rtps->getRTPSParticipant(), rtps, proxy->message_sender());
      group.add_gap(
        sample, eprosima::fastrtps::rtps::SequenceNumberSet_t(sample + 1), guid);
    } catch (...) {
      // a send that timed out: the reader still gets the GAP when it asks, as before
    }
  }
}

bool write_serialized_w_timestamp(
  eprosima::fastdds::dds::DataWriter * writer, const void * data, size_t length,
  int64_t source_timestamp_ns, std::string * error)
{
  if (source_timestamp_ns < 0 || source_timestamp_ns > kMaxSourceTimestampNs) {
    *error = "source timestamp out of range";
    return false;
  }
  // What rmw_publish_serialized_message (rmw_fastrtps_shared_cpp, Jazzy) hands the writer: a
  // fastcdr Cdr over the caller's bytes, positioned at their end, wrapped in SerializedData of
  // type CDR_BUFFER. rmw's TypeSupport::serialize then copies get_serialized_data_length()
  // bytes from the start of the buffer into the DDS payload. Nothing writes to `data`.
  eprosima::fastcdr::FastBuffer buffer(
    static_cast<char *>(const_cast<void *>(data)), length);
  eprosima::fastcdr::Cdr ser(
    buffer, eprosima::fastcdr::Cdr::DEFAULT_ENDIAN, eprosima::fastcdr::CdrVersion::XCDRv1);
  ser.set_encoding_flag(eprosima::fastcdr::EncodingAlgorithmFlag::PLAIN_CDR);
  if (!ser.jump(length)) {
    *error = "cannot position the CDR stream at the end of the serialized data";
    return false;
  }
  rmw_fastrtps_shared_cpp::SerializedData payload;
  payload.type = rmw_fastrtps_shared_cpp::FASTRTPS_SERIALIZED_DATA_TYPE_CDR_BUFFER;
  payload.data = &ser;
  payload.impl = nullptr;  // unused for CDR_BUFFER
  const eprosima::fastrtps::Time_t stamp(
    static_cast<int32_t>(source_timestamp_ns / 1000000000LL),
    static_cast<uint32_t>(source_timestamp_ns % 1000000000LL));
  const ReturnCode_t rc =
    writer->write_w_timestamp(&payload, eprosima::fastdds::dds::HANDLE_NIL, stamp);
  if (rc != ReturnCode_t::RETCODE_OK) {
    *error = "DataWriter::write_w_timestamp failed (return code " + std::to_string(rc()) + ")";
    return false;
  }
  return true;
}

namespace
{

/// The parts of an rmw_fastrtps_cpp publisher whose type's rosidl_typesupport_fastrtps_c
/// callbacks are `callbacks`; false with *error (and *type_mismatch for another type).
bool typed_publisher_parts(
  rmw_publisher_t * publisher, const void * callbacks, rmw_private::PublisherParts * info,
  bool * type_mismatch, std::string * error)
{
  *type_mismatch = false;
  if (!rmw_private::publisher_parts(publisher, info, error)) {
    return false;
  }
  if (info->type_support_impl != callbacks) {
    *type_mismatch = true;
    *error = "the message's type is not the publisher's";
    return false;
  }
  return true;
}

}  // namespace

bool write_message_w_timestamp(
  rmw_publisher_t * publisher, const void * ros_message, const void * callbacks,
  int64_t source_timestamp_ns, bool * type_mismatch, std::string * error)
{
  *type_mismatch = false;
  if (source_timestamp_ns < 0 || source_timestamp_ns > kMaxSourceTimestampNs) {
    *error = "source timestamp out of range";
    return false;
  }
  rmw_private::PublisherParts info;
  if (!typed_publisher_parts(publisher, callbacks, &info, type_mismatch, error)) {
    return false;
  }
  // What rmw_publish (rmw_fastrtps_shared_cpp, Jazzy) hands the writer.
  rmw_fastrtps_shared_cpp::SerializedData payload;
  payload.type = rmw_fastrtps_shared_cpp::FASTRTPS_SERIALIZED_DATA_TYPE_ROS_MESSAGE;
  payload.data = const_cast<void *>(ros_message);
  payload.impl = const_cast<void *>(info.type_support_impl);
  const eprosima::fastrtps::Time_t stamp(
    static_cast<int32_t>(source_timestamp_ns / 1000000000LL),
    static_cast<uint32_t>(source_timestamp_ns % 1000000000LL));
  const ReturnCode_t rc =
    info.writer->write_w_timestamp(&payload, eprosima::fastdds::dds::HANDLE_NIL, stamp);
  if (rc != ReturnCode_t::RETCODE_OK) {
    *error = "DataWriter::write_w_timestamp failed (return code " + std::to_string(rc()) + ")";
    return false;
  }
  return true;
}

bool write_cdr_w_timestamp(
  rmw_publisher_t * publisher, const void * data, size_t length, const void * callbacks,
  int64_t source_timestamp_ns, bool * type_mismatch, std::string * error)
{
  rmw_private::PublisherParts info;
  return typed_publisher_parts(publisher, callbacks, &info, type_mismatch, error) &&
         write_serialized_w_timestamp(info.writer, data, length, source_timestamp_ns, error);
}

bool matched_reader_gids(
  rmw_publisher_t * publisher, std::vector<GidArray> * gids, std::string * error)
{
  rmw_private::PublisherParts info;
  if (!rmw_private::publisher_parts(publisher, &info, error)) {
    return false;
  }
  gids->clear();
  std::vector<eprosima::fastdds::dds::InstanceHandle_t> handles;
  const ReturnCode_t rc = info.writer->get_matched_subscriptions(handles);
  if (rc == ReturnCode_t::RETCODE_OK) {
    // A matched reader's instance handle is its GUID.
    for (const auto & handle : handles) {
      gids->push_back(to_gid_array(eprosima::fastrtps::rtps::iHandle2GUID(handle)));
    }
    return true;
  }
  if (rc != ReturnCode_t::RETCODE_UNSUPPORTED) {
    *error = "DataWriter::get_matched_subscriptions failed (return code " +
      std::to_string(rc()) + ")";
    return false;
  }
  // Fast DDS 2.14: unsupported. rmw's own set of matched readers.
  std::vector<eprosima::fastrtps::rtps::GUID_t> matched;
  if (!rmw_private::rmw_matched_readers(publisher, &matched, error)) {
    return false;
  }
  gids->reserve(matched.size());
  for (const auto & guid : matched) {
    gids->push_back(to_gid_array(guid));
  }
  return true;
}

}  // namespace rbpy_dds
