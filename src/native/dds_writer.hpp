// DataWriter helpers shared by publish_serialized/matched_subscription_gids (dds_endpoints.cpp)
// and ChannelPublisher (dds_channels.cpp). Plain C++: no Python, call them with the GIL
// released.
#ifndef ROSIDL_BUFFER_PY_NATIVE__DDS_WRITER_HPP_
#define ROSIDL_BUFFER_PY_NATIVE__DDS_WRITER_HPP_

#include <array>
#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include "rmw/types.h"

namespace eprosima
{
namespace fastdds
{
namespace dds
{
class DataWriter;
}  // namespace dds
}  // namespace fastdds
}  // namespace eprosima

namespace rbpy_dds
{

/// Largest source timestamp Fast DDS can carry (Time_t: int32 seconds, 0x7fffffff = infinite).
constexpr int64_t kMaxSourceTimestampNs = static_cast<int64_t>(0x7fffffff) * 1000000000LL - 1;

/// Write already-serialized CDR (with its 4-byte encapsulation header) on a DataWriter created
/// by rmw_fastrtps_cpp, with `source_timestamp_ns` (0..kMaxSourceTimestampNs) as the sample's
/// source timestamp. Same payload type rmw_publish_serialized_message hands Fast DDS, so rmw's
/// TypeSupport copies the bytes into the DDS payload; `data` is only read, and not kept.
/// Returns true, or false with a message in *error.
bool write_serialized_w_timestamp(
  eprosima::fastdds::dds::DataWriter * writer, const void * data, size_t length,
  int64_t source_timestamp_ns, std::string * error);

/// Write a C ROS message on the DataWriter of an rmw_fastrtps_cpp publisher (identifier already
/// checked) with `source_timestamp_ns` as the sample's source timestamp: what rmw_publish does,
/// plus the timestamp. rmw's TypeSupport serializes the message straight into the DDS payload.
/// `callbacks` are the message's rosidl_typesupport_fastrtps_c callbacks; a writer of another
/// type is refused (*type_mismatch set). Returns true, or false with a message in *error.
bool write_message_w_timestamp(
  rmw_publisher_t * publisher, const void * ros_message, const void * callbacks,
  int64_t source_timestamp_ns, bool * type_mismatch, std::string * error);

/// write_serialized_w_timestamp on the DataWriter of an rmw_fastrtps_cpp publisher (identifier
/// already checked) whose type's rosidl_typesupport_fastrtps_c callbacks are `callbacks`: CDR
/// the caller serialized for that type. A writer of another type is refused (*type_mismatch
/// set), as write_message_w_timestamp refuses it. Returns true, or false with *error.
bool write_cdr_w_timestamp(
  rmw_publisher_t * publisher, const void * data, size_t length, const void * callbacks,
  int64_t source_timestamp_ns, bool * type_mismatch, std::string * error);

using GidArray = std::array<uint8_t, RMW_GID_STORAGE_SIZE>;

/// Keep the next sample written on the DataWriter of an rmw_fastrtps_cpp publisher (identifier
/// already checked) from the matched readers `readers` (rmw GIDs): Fast DDS then sends them a
/// GAP, not the sample. Installs the writer's exclusion filter on first use (it chains to the
/// filter Fast DDS had installed, for content-filtered readers). Registering again before the
/// write replaces the entry. *available is false (and nothing registered) when this writer
/// cannot be filtered: the private-layout check failed, or another filter is installed.
/// Returns true, or false with *error.
bool exclude_from_next_write(
  rmw_publisher_t * publisher, const std::vector<GidArray> & readers, bool * available,
  std::string * error);

/// Call right after a write on a main-topic DataWriter (never a channel's): send a GAP for the
/// sample just written to each reliable reader exclude_from_next_write kept it from. Fast DDS
/// would send it only when the reader asks, and a KEEP_LAST writer may have dropped the sample
/// by then: a reader whose process was stalled would count it lost. Nothing when none was kept.
void gap_to_excluded_readers(eprosima::fastdds::dds::DataWriter * writer);

/// Remove the exclusion filter from the publisher's writer, giving Fast DDS's own back; call it
/// before the publisher is destroyed. Nothing to do when none was installed.
bool remove_write_exclusions(rmw_publisher_t * publisher, std::string * error);

/// The rmw GIDs (Fast DDS GUIDs) of the DataReaders matched with the DataWriter of an
/// rmw_fastrtps_cpp publisher (identifier already checked). Asks the DataWriter first; Fast DDS
/// 2.14 answers RETCODE_UNSUPPORTED, and then rmw's own set of matched readers (the one behind
/// rmw_publisher_count_matched_subscriptions) is read. Returns true, or false with *error.
bool matched_reader_gids(
  rmw_publisher_t * publisher, std::vector<GidArray> * gids, std::string * error);

}  // namespace rbpy_dds

#endif  // ROSIDL_BUFFER_PY_NATIVE__DDS_WRITER_HPP_
