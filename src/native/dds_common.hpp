// Shared helpers of the rmw_fastrtps layer of rosidl_buffer_py._native (the dds_*.cpp files).
//
// Everything here runs with the GIL held unless a comment says otherwise.
#ifndef ROSIDL_BUFFER_PY_NATIVE__DDS_COMMON_HPP_
#define ROSIDL_BUFFER_PY_NATIVE__DDS_COMMON_HPP_

#include "py_glue.hpp"

#include <array>
#include <cstdint>
#include <string>
#include <vector>

#include "rcutils/error_handling.h"
#include "rmw/serialized_message.h"
#include "rmw/types.h"
#include "rosidl_runtime_c/message_type_support_struct.h"
#include "rosidl_typesupport_fastrtps_cpp/message_type_support.h"

namespace rbpy_dds
{

/// The only rmw implementation this layer supports.
constexpr const char * kFastrtpsIdentifier = "rmw_fastrtps_cpp";

/// Module exceptions: DdsError(RuntimeError) and UnsupportedRmwError(DdsError).
extern PyObject * DdsError;
extern PyObject * UnsupportedRmwError;

using rbpy_glue::GilRelease;
using rbpy_glue::PendingError;
using rbpy_glue::without_gil;

/// A C pointer handed over from Python, optionally pinned.
///
/// Accepted forms: an int (the caller guarantees the pointee outlives every use); an rclpy
/// handle (an object with `.pointer`, e.g. `node.handle`); an rclpy entity whose `.handle` is
/// such a handle (Node, Publisher, Subscription, GuardCondition). Handles are *pinned*: their
/// context manager is entered, so rclpy defers destroying the rcl object (destroy_node(),
/// destroy_publisher(), ...) until release().
class PinnedHandle
{
public:
  PinnedHandle() = default;
  ~PinnedHandle() {release();}
  PinnedHandle(const PinnedHandle &) = delete;
  PinnedHandle & operator=(const PinnedHandle &) = delete;

  /// Resolve `arg` (GIL held). Returns 0, or -1 with a TypeError/ValueError set.
  int acquire(PyObject * arg, const char * what);
  /// Leave the handle's context and drop the reference (GIL held). Idempotent.
  void release();
  void * get() const {return ptr_;}

  /// Resolve the pointer of `arg` without pinning it (GIL held). nullptr with an exception.
  static void * peek(PyObject * arg, const char * what);

private:
  PyObject * handle_ = nullptr;  // owned, entered; NULL for plain ints
  void * ptr_ = nullptr;
};

/// Guard against passing the wrong kind of rclpy object where a raw cast would follow: unless
/// `arg` is a pointer int, its handle's (or its own) type must be named `<module>.<kind>`
/// (kind "Publisher" / "Subscription" / ...). Returns 0, or -1 with TypeError (GIL held).
int check_handle_kind(PyObject * arg, const char * kind, const char * what);

/// Read and clear the calling thread's rcutils/rmw error string (GIL not needed).
std::string take_rmw_error();

/// Raise DdsError("<what>: <rmw error>"); returns NULL.
PyObject * raise_rmw_error(const std::string & what, const std::string & rmw_error);

/// 16-byte GID bytes object.
PyObject * gid_bytes(const uint8_t * data);

using GidArray = std::array<uint8_t, RMW_GID_STORAGE_SIZE>;

/// list[bytes] of 16-byte GIDs.
PyObject * gid_list(const std::vector<GidArray> & gids);

/// Parse a source timestamp (int, ns since the epoch, 0 <= t < 2**31 s). Returns 0, or -1
/// with TypeError/ValueError set.
int parse_source_timestamp(PyObject * arg, int64_t * out);

/// rclpy-like message info dict (source_timestamp, received_timestamp,
/// publication_sequence_number, reception_sequence_number, from_intra_process).
PyObject * message_info_dict(const rmw_message_info_t & info);

/// Parse an endpoint kind: "publisher"/"writer" -> true, "subscription"/"reader" -> false.
/// Returns 0 or -1 with ValueError.
int parse_kind(const char * kind, bool * is_publisher);

/// Raise UnsupportedRmwError unless `identifier` is rmw_fastrtps_cpp. Returns 0 or -1.
int check_identifier(const char * identifier, const char * what);

/// The rmw_fastrtps handle behind a pinned rcl entity (`get` is rcl_{node,publisher,
/// subscription}_get_rmw_handle, called with the GIL released). nullptr with DdsError when
/// the rcl entity is not valid, UnsupportedRmwError when it is another rmw's (GIL held).
template<typename Rmw, typename Rcl>
Rmw * fastrtps_handle(void * rcl_entity, Rmw * (*get)(const Rcl *), const char * what)
{
  Rmw * handle = without_gil([&] {return get(static_cast<const Rcl *>(rcl_entity));});
  if (handle == nullptr) {
    rcutils_reset_error();
    PyErr_Format(DdsError, "the rcl %s is not valid (already destroyed?)", what);
    return nullptr;
  }
  return check_identifier(handle->implementation_identifier, what) < 0 ? nullptr : handle;
}

/// Pin an rclpy publisher (or its handle; a pointer int is trusted) into `pin`; its rmw
/// publisher, or nullptr with TypeError/DdsError/UnsupportedRmwError (GIL held).
rmw_publisher_t * pin_rmw_publisher(PyObject * arg, const char * what, PinnedHandle * pin);

/// Pin an rclpy node (or its handle) into `pin`; its rmw node, or nullptr with
/// TypeError/DdsError/UnsupportedRmwError (GIL held).
rmw_node_t * pin_rmw_node(PyObject * arg, PinnedHandle * pin);

/// The C side of a generated ROS message class, as rclpy's own publish and take use it: the
/// type support and the functions rosidl_generator_py attaches to the class (_CREATE_ROS_MESSAGE,
/// _DESTROY_ROS_MESSAGE, _CONVERT_FROM_PY, _CONVERT_TO_PY). Valid while the class lives.
struct MessageSupport
{
  const rosidl_message_type_support_t * type_support = nullptr;
  void * (*create)() = nullptr;
  void (*destroy)(void *) = nullptr;
  bool (*from_py)(PyObject *, void *) = nullptr;
  PyObject * (*to_py)(void *) = nullptr;
  /// The rosidl_typesupport_fastrtps_c callbacks of the type (what rmw_fastrtps_cpp stores as
  /// a DataWriter's type_support_impl_).
  const message_type_support_callbacks_t * callbacks = nullptr;

  /// Read them from `msg_class` (GIL held). Returns 0, or -1 with TypeError.
  int load(PyObject * msg_class);
};

/// A C message owned for the duration of a call: created on demand by create() (plain C,
/// no GIL needed), destroyed with this object. `support` may be null when none is needed.
class OwnedRosMessage
{
public:
  explicit OwnedRosMessage(const MessageSupport * support)
  : support_(support) {}
  ~OwnedRosMessage() {if (msg_) {support_->destroy(msg_);}}
  OwnedRosMessage(const OwnedRosMessage &) = delete;
  OwnedRosMessage & operator=(const OwnedRosMessage &) = delete;
  /// The message, created on first call; nullptr when out of memory.
  void * create() {return msg_ ? msg_ : (msg_ = support_->create());}
  void * get() const {return msg_;}

private:
  const MessageSupport * support_;
  void * msg_ = nullptr;
};

/// A bytes copy of serialized CDR (GIL held).
PyObject * serialized_bytes(const rmw_serialized_message_t & serialized);

/// `(data, publisher_gid, info)` of a take, and `extra` as a fourth item when given (borrowed);
/// takes over `data` (nullptr: an exception is set).
PyObject * taken_tuple(
  PyObject * data, const rmw_message_info_t & info, PyObject * extra = nullptr);

/// A caller's serialized CDR (any C-contiguous buffer holding at least the 4-byte
/// encapsulation header), held for the duration of a call. Read it without the GIL.
class SerializedView
{
public:
  SerializedView() = default;
  ~SerializedView() {if (held_) {PyBuffer_Release(&view_);}}
  SerializedView(const SerializedView &) = delete;
  SerializedView & operator=(const SerializedView &) = delete;
  /// Returns 0, or -1 with BufferError/TypeError/ValueError (GIL held).
  int acquire(PyObject * data);
  void * data() const {return view_.buf;}
  size_t size() const {return static_cast<size_t>(view_.len);}

private:
  Py_buffer view_{};
  bool held_ = false;
};

/// Whether a sample of this length is to be deserialized (max_size < 0: any length).
inline bool fits(const rmw_serialized_message_t & serialized, Py_ssize_t max_size)
{
  return max_size < 0 || serialized.buffer_length <= static_cast<size_t>(max_size);
}

/// Deserialize `serialized` into `ros_message`, creating it (GIL not needed), as rmw_deserialize
/// does. False when the bytes do not deserialize or are not XCDR1 (encapsulation
/// 0x0000/0x0001, the only ones rosidl_buffer_py.codec reads): hand serialized_bytes() to the
/// codec then. On success, convert with `support.to_py(ros_message.get())` (GIL held).
bool try_deserialize(
  const MessageSupport & support, const rmw_serialized_message_t & serialized,
  OwnedRosMessage * ros_message);

/// The message a slot program (rosidl_buffer_py/codec/plans.py) builds from CDR with its
/// encapsulation header, the one deserialize_message gives; nullptr, no exception set, when the
/// program is None or cannot build it exactly so (codec_fast.cpp). GIL held.
PyObject * build_from_cdr(PyObject * program, const uint8_t * data, size_t length);

/// The descriptor message in `data` (CDR with its encapsulation header) as the tuple
/// (message without its payload, backend_type, descriptor bytes): codec_fast's
/// decode_descriptor; nullptr, no exception set, for anything else (CPU bytes, malformed
/// input, a control message), which the Python codec then reads. GIL held.
PyObject * decode_described(
  const uint8_t * data, size_t size, PyObject * msg_class, PyObject * ops,
  Py_ssize_t suffix_size, Py_ssize_t max_descriptor, PyObject * program);

/// `msg`'s CDR (encapsulation header, zero padding) written from its slots by a slot program,
/// the bytes the type support writes for what convert_from_py makes of it; false (no exception
/// set) when the program is None or cannot write it exactly so. GIL held.
bool write_from_slots(PyObject * msg, PyObject * program, std::vector<char> * out);

/// The same with the payload field as a descriptor (its marker, the backend's name, the
/// descriptor): the bytes codec.encode(msg, (backend, descriptor)) gives; false (no exception
/// set) when the program is None or cannot write them exactly so. GIL held.
bool write_described_from_slots(
  PyObject * msg, PyObject * program, const char * backend, Py_ssize_t backend_length,
  const char * descriptor, Py_ssize_t descriptor_length, std::vector<char> * out);

/// DdsError("<what>: <rmw error>") to raise once the GIL is back (GIL not needed).
inline void set_rmw_error(PendingError * error, const std::string & what)
{
  error->set(DdsError, what + ": " + take_rmw_error());
}

// The function tables of each part and the channel types (added by add_dds_api).
extern PyMethodDef endpoint_functions[];   // dds_endpoints.cpp
extern PyMethodDef discovery_functions[];  // dds_discovery.cpp
extern PyMethodDef channel_functions[];    // dds_channels.cpp
extern PyMethodDef codec_functions[];      // codec_fast.cpp
int add_channel_types(PyObject * module);  // dds_channels.cpp

}  // namespace rbpy_dds

/// Add the rmw_fastrtps layer (functions, ChannelPublisher, ChannelSubscription, exceptions)
/// to `module`. Returns 0 or -1 with an exception set.
int add_dds_api(PyObject * module);

#endif  // ROSIDL_BUFFER_PY_NATIVE__DDS_COMMON_HPP_
