// Every access of rosidl_buffer_py._native to rmw_fastrtps's and Fast DDS's private memory layout,
// and the one place that replaces an object rmw owns (its participant listener). See the .cpp for what each
// mirrors. Plain C++, no Python; all of it refuses to run until the Python side has verified
// that the running rmw_fastrtps_cpp, rmw_fastrtps_shared_cpp and Fast DDS are the versions this
// extension was built against (set_layout_verified, called by rosidl_buffer_py._dds at import).
#ifndef ROSIDL_BUFFER_PY_NATIVE__RMW_FASTRTPS_PRIVATE_HPP_
#define ROSIDL_BUFFER_PY_NATIVE__RMW_FASTRTPS_PRIVATE_HPP_

#include <cstdint>
#include <string>
#include <vector>

#include "fastdds/rtps/common/Guid.h"
#include "rmw/types.h"

namespace eprosima
{
namespace fastdds
{
namespace dds
{
class DataWriter;
class DomainParticipant;
class DomainParticipantListener;
class Subscriber;
}  // namespace dds
}  // namespace fastdds
namespace fastrtps
{
namespace rtps
{
class RTPSWriter;
}  // namespace rtps
}  // namespace fastrtps
}  // namespace eprosima

namespace rbpy_dds
{
namespace rmw_private
{

/// Versions this extension was compiled against: (package, version) pairs for
/// rmw_fastrtps_cpp, rmw_fastrtps_shared_cpp (from their package.xml, passed by setup.py) and
/// fastrtps (Fast DDS, from its config.h).
struct BuiltVersion
{
  const char * package;
  const char * version;
};
const std::vector<BuiltVersion> & built_versions();

/// Whether the running libraries were verified to be those versions (default false).
bool layout_verified();
void set_layout_verified(bool verified);

/// The DataWriter and type support of an rmw_fastrtps_cpp publisher (identifier already
/// checked), read from rmw's CustomPublisherInfo. False with *error when not verified or absent.
struct PublisherParts
{
  eprosima::fastdds::dds::DataWriter * writer = nullptr;
  const void * type_support_impl = nullptr;
};
bool publisher_parts(rmw_publisher_t * publisher, PublisherParts * parts, std::string * error);

/// rmw's own set of the readers matched with the publisher (the one behind
/// rmw_publisher_count_matched_subscriptions), copied under its mutex.
bool rmw_matched_readers(
  rmw_publisher_t * publisher, std::vector<eprosima::fastrtps::rtps::GUID_t> * guids,
  std::string * error);

/// Set the participant's listener (our discovery tap, rmw's own back, or nullptr to stop
/// listening), keeping its status mask; waits for running discovery callbacks in bounded steps,
/// never with Fast DDS's default wait (see the .cpp). False with *error when not verified or
/// when callbacks kept running for 30 s.
bool set_participant_listener(
  eprosima::fastdds::dds::DomainParticipant * participant,
  eprosima::fastdds::dds::DomainParticipantListener * listener, std::string * error);

/// The RTPSWriter behind a DataWriter (Fast DDS keeps it in the private DataWriterImpl), checked
/// to be the one: its publisher and GUID must be the DataWriter's. nullptr with *error when not
/// verified or when the check fails.
eprosima::fastrtps::rtps::RTPSWriter * rtps_writer_of(
  eprosima::fastdds::dds::DataWriter * writer, std::string * error);

/// Whether `filter` is the DataWriter's own reader filter (its DataWriterImpl, which Fast DDS
/// installs on the RTPSWriter for content-filtered readers).
bool is_own_reader_filter(
  eprosima::fastdds::dds::DataWriter * writer, const void * filter);

/// The sequence number the RTPSWriter gives its next sample (from its WriterHistory, a
/// protected member of the public RTPSWriter). Read it only while nothing else writes.
int64_t next_sequence_number(eprosima::fastrtps::rtps::RTPSWriter * writer);

/// The Subscriber rmw creates every DataReader of the node's participant with
/// (CustomParticipantInfo::subscriber_), checked to belong to the node's DomainParticipant;
/// nullptr with `error` otherwise.
eprosima::fastdds::dds::Subscriber * rmw_subscriber_of(rmw_node_t * node, std::string * error);

/// Hold back (`hold` true) or let go the enabling of the DataWriters (`writers` true: rmw's one
/// Publisher, CustomParticipantInfo::publisher_) or DataReaders (its subscriber_) that rmw creates
/// with the node's participant. While held they are created disabled: their QoS, USER_DATA
/// included, is set without discovery traffic. Letting go enables every one of them left
/// disabled. Call with the GIL held (rclpy creates its entities with it held). False with
/// *error when not verified, when rmw's participant info does not have the expected layout, or
/// when Fast DDS refuses to enable one.
bool hold_enabling(rmw_node_t * node, bool writers, bool hold, std::string * error);

/// Whether `node` is the only node of its context: rmw_fastrtps destroys the context's
/// participant when that node is destroyed (rmw_context_impl_s::count, the nodes' reference
/// count, read under the context's mutex). False with *error when not verified.
bool only_node_of_context(rmw_node_t * node, std::string * error);

}  // namespace rmw_private
}  // namespace rbpy_dds

#endif  // ROSIDL_BUFFER_PY_NATIVE__RMW_FASTRTPS_PRIVATE_HPP_
