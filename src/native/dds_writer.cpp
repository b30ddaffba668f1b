// DataWriter helpers (see dds_writer.hpp). No Python in here.
#include "dds_writer.hpp"


#include "fastcdr/Cdr.h"
#include "fastcdr/FastBuffer.h"
#include "fastdds/dds/common/InstanceHandle.hpp"
#include "fastdds/dds/publisher/DataWriter.hpp"
#include "fastdds/rtps/common/InstanceHandle.h"
#include "fastdds/rtps/common/Time_t.h"
#include "rmw_fastrtps_private.hpp"
#include "rmw_fastrtps_shared_cpp/TypeSupport.hpp"
#include "rmw_fastrtps_shared_cpp/guid_utils.hpp"

namespace rbpy_dds
{

using eprosima::fastrtps::types::ReturnCode_t;

namespace
{

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
  rmw_private::PublisherParts info;
  if (!rmw_private::publisher_parts(publisher, &info, error)) {
    return false;
  }
  if (info.type_support_impl != callbacks) {
    *type_mismatch = true;
    *error = "the message's type is not the publisher's";
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
