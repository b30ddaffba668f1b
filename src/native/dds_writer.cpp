// DataWriter helpers (see dds_writer.hpp). No Python in here.
#include "dds_writer.hpp"

#include <mutex>
#include <set>

#include "fastcdr/Cdr.h"
#include "fastcdr/FastBuffer.h"
#include "fastdds/dds/common/InstanceHandle.hpp"
#include "fastdds/dds/publisher/DataWriter.hpp"
#include "fastdds/rtps/common/InstanceHandle.h"
#include "fastdds/rtps/common/Time_t.h"
#include "rmw_fastrtps_shared_cpp/TypeSupport.hpp"
#include "rmw_fastrtps_shared_cpp/custom_publisher_info.hpp"
#include "rmw_fastrtps_shared_cpp/guid_utils.hpp"

namespace rbpy_dds
{

using eprosima::fastrtps::types::ReturnCode_t;

namespace
{

// Read access to RMWPublisherEvent's private set of matched readers (and its mutex). rmw keeps
// it from on_publication_matched (+1 insert, -1 erase of last_subscription_handle's GUID) and
// counts it in rmw_publisher_count_matched_subscriptions, but has no accessor for it. The
// standard's rule that explicit instantiations skip access checks lets us name the members;
// their layout comes from the header installed with the rmw_fastrtps_shared_cpp library
// that rmw_fastrtps_cpp loads (same build; Jazzy keeps its ABI).
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

GidArray to_gid_array(const eprosima::fastrtps::rtps::GUID_t & guid)
{
  GidArray gid{};
  rmw_fastrtps_shared_cpp::copy_from_fastrtps_guid_to_byte_array(guid, gid.data());
  return gid;
}

}  // namespace

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

bool write_message_w_timestamp(
  rmw_publisher_t * publisher, const void * ros_message, const void * callbacks,
  int64_t source_timestamp_ns, bool * type_mismatch, std::string * error)
{
  *type_mismatch = false;
  if (source_timestamp_ns < 0 || source_timestamp_ns > kMaxSourceTimestampNs) {
    *error = "source timestamp out of range";
    return false;
  }
  auto * info = static_cast<CustomPublisherInfo *>(publisher->data);
  if (info == nullptr || info->data_writer_ == nullptr) {
    *error = "the publisher has no DataWriter";
    return false;
  }
  if (info->type_support_impl_ != callbacks) {
    *type_mismatch = true;
    *error = "the message's type is not the publisher's";
    return false;
  }
  // What rmw_publish (rmw_fastrtps_shared_cpp, Jazzy) hands the writer.
  rmw_fastrtps_shared_cpp::SerializedData payload;
  payload.type = rmw_fastrtps_shared_cpp::FASTRTPS_SERIALIZED_DATA_TYPE_ROS_MESSAGE;
  payload.data = const_cast<void *>(ros_message);
  payload.impl = info->type_support_impl_;
  const eprosima::fastrtps::Time_t stamp(
    static_cast<int32_t>(source_timestamp_ns / 1000000000LL),
    static_cast<uint32_t>(source_timestamp_ns % 1000000000LL));
  const ReturnCode_t rc =
    info->data_writer_->write_w_timestamp(&payload, eprosima::fastdds::dds::HANDLE_NIL, stamp);
  if (rc != ReturnCode_t::RETCODE_OK) {
    *error = "DataWriter::write_w_timestamp failed (return code " + std::to_string(rc()) + ")";
    return false;
  }
  return true;
}

bool matched_reader_gids(
  rmw_publisher_t * publisher, std::vector<GidArray> * gids, std::string * error)
{
  auto * info = static_cast<CustomPublisherInfo *>(publisher->data);
  if (info == nullptr || info->data_writer_ == nullptr || info->publisher_event_ == nullptr) {
    *error = "the rmw publisher has no DataWriter";
    return false;
  }
  gids->clear();
  std::vector<eprosima::fastdds::dds::InstanceHandle_t> handles;
  const ReturnCode_t rc = info->data_writer_->get_matched_subscriptions(handles);
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
  // Fast DDS 2.14: unsupported. rmw's set, under its mutex (which only its listener's
  // on_publication_matched takes, briefly and without calling out).
  RMWPublisherEvent * event = info->publisher_event_;
  std::lock_guard<std::mutex> lock(event->*member_of(MatchedMutexTag{}));
  const auto & matched = event->*member_of(MatchedSetTag{});
  gids->reserve(matched.size());
  for (const auto & guid : matched) {
    gids->push_back(to_gid_array(guid));
  }
  return true;
}

}  // namespace rbpy_dds
