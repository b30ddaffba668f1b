// The descriptor form of rosidl_buffer_py.codec in C: the hot path of every descriptor message.
//
//   encode_descriptor(msg, slots, payload_slot, empty, backend, descriptor, suffix_size)
//       -> bytearray | None
//   decode_descriptor(raw, msg_class, prefix_ops, suffix_size, max_descriptor)
//       -> (msg, backend_type, descriptor) | None
//
// Both do what the Python codec does (same bytes out, same message out) without running Python
// code per message: a descriptor message is small, so its cost was interpreter work, which a
// process woken for one frame pays with cold caches (about 0.1 ms each way at 20 Hz). Each
// handles the well-formed case only and returns None for anything else (not a descriptor,
// malformed input, a value it cannot convert): the Python codec then runs and raises its
// CodecError naming the problem, so error reporting has one implementation.
#include <cstring>
#include <exception>
#include <vector>

#include "dds_common.hpp"

#include "fastcdr/Cdr.h"
#include "fastcdr/FastBuffer.h"

namespace rbpy_dds
{
namespace
{

constexpr size_t kHeader = 4;
constexpr uint32_t kMarker = 0xFFFFFFFFu;
// The op kinds of rosidl_buffer_py/codec/walker.py (FIXED, STRING, PSEQ, SEQ, ARRAY). Each op is
// a typing.NamedTuple (a tuple subclass, so PyTuple_Check holds), read here by position: the
// kind first, then FixedOp(kind, align, size, inner_pads, label), StringOp(kind, bound, label),
// PrimitiveSeqOp(kind, align, itemsize, bound, label), SeqOp(kind, sub_ops, min_size, bound,
// label, path) and ArrayOp(kind, sub_ops, count, label, path). That field order is what this
// file reads (test_codec.py's test_op_fields_are_in_the_order_the_fast_path_reads pins it); any
// other kind (BlobOp, WStringOp) makes walk() answer false.
enum OpKind : long {kFixed = 0, kString = 1, kPseq = 2, kSeq = 3, kArray = 4};

struct Reader
{
  const uint8_t * body;  // the CDR origin (after the encapsulation header)
  size_t end;
  bool little;

  /// The 4-aligned uint32 at or after `*pos`; false when it does not fit.
  bool u32(size_t * pos, uint32_t * value) const
  {
    size_t start = (*pos + 3) & ~static_cast<size_t>(3);
    if (start > end || end - start < 4) {
      return false;
    }
    const uint8_t * p = body + start;
    *value = little ?
      (uint32_t(p[0]) | uint32_t(p[1]) << 8 | uint32_t(p[2]) << 16 | uint32_t(p[3]) << 24) :
      (uint32_t(p[3]) | uint32_t(p[2]) << 8 | uint32_t(p[1]) << 16 | uint32_t(p[0]) << 24);
    *pos = start + 4;
    return true;
  }
};

bool item(PyObject * op, Py_ssize_t index, Py_ssize_t * value)
{
  PyObject * o = PyTuple_GET_ITEM(op, index);
  if (o == Py_None) {
    *value = -1;
    return true;
  }
  *value = PyLong_AsSsize_t(o);
  return !(*value == -1 && PyErr_Occurred());
}

/// codec.walker.walk without pads: every check it makes, false where it would raise.
bool walk(PyObject * ops, const Reader & r, size_t * pos, int depth)
{
  if (!PyTuple_Check(ops) || depth > 64) {
    return false;
  }
  for (Py_ssize_t i = 0; i < PyTuple_GET_SIZE(ops); ++i) {
    PyObject * op = PyTuple_GET_ITEM(ops, i);
    Py_ssize_t kind, a, b, c;
    if (!PyTuple_Check(op) || PyTuple_GET_SIZE(op) < 3 || !item(op, 0, &kind)) {
      return false;
    }
    if (kind == kFixed) {
      if (!item(op, 1, &a) || !item(op, 2, &b) || a < 1 || b < 0) {
        return false;
      }
      size_t start = (*pos + a - 1) & ~static_cast<size_t>(a - 1);
      if (start > r.end || r.end - start < static_cast<size_t>(b)) {
        return false;
      }
      *pos = start + b;
    } else if (kind == kString) {
      uint32_t length;
      if (!item(op, 1, &a) || !r.u32(pos, &length) || length == 0 ||
        length > r.end - *pos || r.body[*pos + length - 1] != 0 ||
        (a >= 0 && length - 1 > static_cast<size_t>(a)))
      {
        return false;
      }
      *pos += length;
    } else if (kind == kPseq) {
      uint32_t count;
      if (PyTuple_GET_SIZE(op) < 4 || !item(op, 1, &a) || !item(op, 2, &b) ||
        !item(op, 3, &c) || a < 1 || b < 1 || !r.u32(pos, &count) ||
        (c >= 0 && count > static_cast<size_t>(c)))
      {
        return false;
      }
      if (count) {
        size_t start = (*pos + a - 1) & ~static_cast<size_t>(a - 1);
        size_t nbytes = size_t(count) * b;
        if (start > r.end || nbytes > r.end - start) {
          return false;
        }
        *pos = start + nbytes;
      }
    } else if (kind == kSeq) {
      uint32_t count;
      if (PyTuple_GET_SIZE(op) < 4 || !item(op, 2, &b) || !item(op, 3, &c) || b < 1 ||
        !r.u32(pos, &count) || (c >= 0 && count > static_cast<size_t>(c)) ||
        size_t(count) * b > r.end - *pos)
      {
        return false;
      }
      for (uint32_t k = 0; k < count; ++k) {
        if (!walk(PyTuple_GET_ITEM(op, 1), r, pos, depth + 1)) {
          return false;
        }
      }
    } else if (kind == kArray) {
      if (!item(op, 2, &b) || b < 0) {
        return false;
      }
      for (Py_ssize_t k = 0; k < b; ++k) {
        if (!walk(PyTuple_GET_ITEM(op, 1), r, pos, depth + 1)) {
          return false;
        }
      }
    } else {
      return false;
    }
  }
  return true;
}

/// None, after clearing any pending exception: the Python codec takes over.
PyObject * fall_back()
{
  PyErr_Clear();
  Py_RETURN_NONE;
}

class BufferView
{
public:
  ~BufferView() {if (held_) {PyBuffer_Release(&view_);}}
  bool get(PyObject * obj)
  {
    held_ = PyObject_GetBuffer(obj, &view_, PyBUF_SIMPLE) == 0;
    return held_;
  }
  const uint8_t * data() const {return static_cast<const uint8_t *>(view_.buf);}
  size_t size() const {return static_cast<size_t>(view_.len);}

private:
  Py_buffer view_;
  bool held_ = false;
};

PyObject * decode_descriptor(PyObject *, PyObject * args)
{
  PyObject * raw;
  PyObject * msg_class;
  PyObject * ops;
  Py_ssize_t suffix_size;
  Py_ssize_t max_descriptor;
  if (!PyArg_ParseTuple(
      args, "OOO!nn:decode_descriptor", &raw, &msg_class, &PyTuple_Type, &ops, &suffix_size,
      &max_descriptor))
  {
    return nullptr;
  }
  BufferView input;
  if (!input.get(raw) || input.size() < kHeader || suffix_size < 0) {
    return fall_back();
  }
  const uint8_t * data = input.data();
  if (data[0] != 0 || data[1] > 1) {
    return fall_back();  // not XCDR1: the codec names the encapsulation
  }
  Reader r{data + kHeader, input.size() - kHeader, data[1] == 1};
  size_t pos = 0;
  uint32_t first;
  if (!walk(ops, r, &pos, 0) || !r.u32(&pos, &first) || first != kMarker) {
    return fall_back();  // CPU bytes (or malformed): the codec's path
  }
  const size_t head_end = kHeader + pos - 4;
  uint32_t length;
  if (!r.u32(&pos, &length) || length < 2 || length > r.end - pos ||
    r.body[pos + length - 1] != 0 ||
    std::memchr(r.body + pos, 0, length - 1) != nullptr)
  {
    return fall_back();
  }
  const char * name = reinterpret_cast<const char *>(r.body + pos);
  const Py_ssize_t name_length = static_cast<Py_ssize_t>(length - 1);
  pos += length;
  uint32_t nbytes;
  if (!r.u32(&pos, &nbytes) || nbytes > static_cast<uint64_t>(max_descriptor) ||
    nbytes > r.end - pos)
  {
    return fall_back();
  }
  const uint8_t * descriptor = r.body + pos;
  const size_t data_end = pos + nbytes;
  if (static_cast<size_t>(suffix_size) > r.end - data_end) {
    return fall_back();
  }
  MessageSupport support;
  if (support.load(msg_class) < 0) {
    return fall_back();
  }
  // The message without its payload: the head, a zero length, the fields after the payload.
  std::vector<uint8_t> small(head_end + 4 + suffix_size);
  std::memcpy(small.data(), data, head_end);
  std::memset(small.data() + head_end, 0, 4);
  std::memcpy(small.data() + head_end + 4, r.body + data_end, suffix_size);
  rmw_serialized_message_t serialized = rmw_get_zero_initialized_serialized_message();
  serialized.buffer = small.data();
  serialized.buffer_length = serialized.buffer_capacity = small.size();
  OwnedRosMessage ros_message(&support);
  if (!try_deserialize(support, serialized, &ros_message)) {
    return fall_back();
  }
  PyObject * msg = support.to_py(ros_message.get());
  if (msg == nullptr) {
    return fall_back();
  }
  PyObject * backend = PyUnicode_DecodeUTF8(name, name_length, "strict");
  PyObject * desc = backend ? PyBytes_FromStringAndSize(
    reinterpret_cast<const char *>(descriptor), nbytes) : nullptr;
  PyObject * result = desc ? PyTuple_Pack(3, msg, backend, desc) : nullptr;
  Py_DECREF(msg);
  Py_XDECREF(backend);
  Py_XDECREF(desc);
  return result ? result : fall_back();
}

/// A copy of `msg` holding `empty` as its payload (the clone of _encode_head in
/// rosidl_buffer_py/codec/encoder.py), or nullptr.
PyObject * payload_free_clone(PyObject * msg, PyObject * slots, PyObject * payload_slot,
  PyObject * empty)
{
  PyTypeObject * type = Py_TYPE(msg);
  PyObject * no_args = PyTuple_New(0);
  PyObject * clone = no_args ? type->tp_new(type, no_args, nullptr) : nullptr;
  Py_XDECREF(no_args);
  if (clone == nullptr) {
    return nullptr;
  }
  for (Py_ssize_t i = 0; i < PyTuple_GET_SIZE(slots); ++i) {
    PyObject * slot = PyTuple_GET_ITEM(slots, i);
    int equal = PyUnicode_Compare(slot, payload_slot) == 0;
    PyObject * value = equal ? (Py_INCREF(empty), empty) : PyObject_GetAttr(msg, slot);
    if (value == nullptr || PyObject_SetAttr(clone, slot, value) < 0) {
      Py_XDECREF(value);
      Py_DECREF(clone);
      return nullptr;
    }
    Py_DECREF(value);
  }
  return clone;
}

PyObject * encode_descriptor(PyObject *, PyObject * args)
{
  PyObject * msg;
  PyObject * slots;
  PyObject * payload_slot;
  PyObject * empty;
  const char * backend;
  Py_ssize_t backend_length;
  const char * descriptor;
  Py_ssize_t descriptor_length;
  Py_ssize_t suffix_size;
  if (!PyArg_ParseTuple(
      args, "OO!UOy#y#n:encode_descriptor", &msg, &PyTuple_Type, &slots, &payload_slot, &empty,
      &backend, &backend_length, &descriptor, &descriptor_length, &suffix_size))
  {
    return nullptr;
  }
  if (suffix_size < 0) {
    return fall_back();
  }
  MessageSupport support;
  if (support.load(reinterpret_cast<PyObject *>(Py_TYPE(msg))) < 0) {
    return fall_back();
  }
  PyObject * clone = payload_free_clone(msg, slots, payload_slot, empty);
  if (clone == nullptr) {
    return fall_back();
  }
  OwnedRosMessage ros_message(&support);
  void * c_msg = ros_message.create();
  const bool converted = c_msg != nullptr && support.from_py(clone, c_msg);
  Py_DECREF(clone);
  if (!converted) {
    return fall_back();
  }
  // Serialized as rmw_serialize does, into zeroed memory: the padding is zero, as encode()'s.
  std::vector<char> buffer(kHeader + support.callbacks->get_serialized_size(c_msg) + 8, 0);
  size_t length;
  try {
    eprosima::fastcdr::FastBuffer fast(buffer.data(), buffer.size());
    eprosima::fastcdr::Cdr ser(
      fast, eprosima::fastcdr::Cdr::DEFAULT_ENDIAN, eprosima::fastcdr::CdrVersion::XCDRv1);
    ser.set_encoding_flag(eprosima::fastcdr::EncodingAlgorithmFlag::PLAIN_CDR);
    ser.serialize_encapsulation();
    if (!support.callbacks->cdr_serialize(c_msg, ser)) {
      return fall_back();
    }
    length = ser.get_serialized_data_length();
  } catch (const std::exception &) {
    return fall_back();
  }
  // The empty payload's uint32 length sits right before the alignment-1 suffix.
  const auto * bytes = reinterpret_cast<const uint8_t *>(buffer.data());
  if (length > buffer.size() || length < kHeader + 4 + static_cast<size_t>(suffix_size) ||
    bytes[0] != 0 || bytes[1] > 1)
  {
    return fall_back();
  }
  const size_t at = length - suffix_size - 4;
  if ((at - kHeader) % 4 != 0 || std::memcmp(bytes + at, "\0\0\0\0", 4) != 0) {
    return fall_back();
  }
  const bool little = bytes[1] == 1;
  auto put_u32 = [little](std::vector<char> & out, uint32_t v) {
      char b[4];
      for (int k = 0; k < 4; ++k) {
        b[little ? k : 3 - k] = static_cast<char>((v >> (8 * k)) & 0xFF);
      }
      out.insert(out.end(), b, b + 4);
    };
  std::vector<char> out;
  out.reserve(at + 16 + backend_length + descriptor_length + suffix_size);
  out.insert(out.end(), buffer.data(), buffer.data() + at);
  put_u32(out, kMarker);
  put_u32(out, static_cast<uint32_t>(backend_length + 1));
  out.insert(out.end(), backend, backend + backend_length);
  out.push_back('\0');
  out.resize(out.size() + ((4 - (out.size() - kHeader) % 4) % 4), '\0');
  put_u32(out, static_cast<uint32_t>(descriptor_length));
  out.insert(out.end(), descriptor, descriptor + descriptor_length);
  out.insert(out.end(), buffer.data() + at + 4, buffer.data() + at + 4 + suffix_size);
  return PyByteArray_FromStringAndSize(out.data(), static_cast<Py_ssize_t>(out.size()));
}

}  // namespace

PyMethodDef codec_functions[] = {
  RBPY_FUNCTION(encode_descriptor, METH_VARARGS,
    "encode_descriptor(msg, slots, payload_slot, empty, backend, descriptor, suffix_size) -> "
    "bytearray | None\n\ncodec.encode(msg, (backend, descriptor)) of a plan (slots, payload "
    "slot, suffix size) in C; `empty` is the empty payload the serialized clone holds. None "
    "when it cannot (the Python codec then raises the CodecError)."),
  RBPY_FUNCTION(decode_descriptor, METH_VARARGS,
    "decode_descriptor(raw, msg_class, prefix_ops, suffix_size, max_descriptor) -> "
    "(msg, backend_type, descriptor) | None\n\ncodec.decode() of descriptor-encoded CDR in C "
    "(the message's payload field left empty). None for CPU bytes and anything malformed: the "
    "Python codec then decodes or rejects it."),
  RBPY_METHODS_END,
};

}  // namespace rbpy_dds
