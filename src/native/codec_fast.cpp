// The descriptor form of rosidl_buffer_py.codec in C: the hot path of every descriptor message.
//
//   encode_descriptor(msg, slots, payload_slot, empty, backend, descriptor, suffix_size,
//       program=None) -> bytearray | None
//   decode_descriptor(raw, msg_class, prefix_ops, suffix_size, max_descriptor, program=None)
//       -> (msg, backend_type, descriptor) | None
//   deserialize(raw, program) -> msg | None   (and build_from_cdr, for the takes in C)
//   serialize(msg, program) -> bytearray | None   (and write_from_slots, for write_message)
//
// Both do what the Python codec does (same bytes out, same message out) without running Python
// code per message: a descriptor message is small, so its cost was interpreter work, which a
// process woken for one frame pays with cold caches (about 0.1 ms each way at 20 Hz). Each
// handles the well-formed case only and returns None for anything else (not a descriptor,
// malformed input, a value it cannot convert): the Python codec then runs and raises its
// CodecError naming the problem, so error reporting has one implementation.
//
// The decoded message is built from its slots where the type allows (a slot program, see
// build()): the generated convert_to_py runs the class's __init__ and one Python setter per
// field, which a woken process pays at about 100 µs for an Image; the slots set from C give the
// same object. Anything the program does not build exactly as the generated code would goes
// to the type support and convert_to_py, as deserialize_message does. The same program writes
// the descriptor message from the slots (write_fields), where convert_from_py would call one
// Python getter per field; values of another type or range than the field's go to the type
// support.
#include <cstdint>
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
constexpr bool kLittleHost = __BYTE_ORDER__ == __ORDER_LITTLE_ENDIAN__;
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

/// An int or None (-1) object as a Py_ssize_t.
bool item_value(PyObject * o, Py_ssize_t * value)
{
  if (o == Py_None) {
    *value = -1;
    return true;
  }
  *value = PyLong_AsSsize_t(o);
  return !(*value == -1 && PyErr_Occurred());
}

bool item(PyObject * op, Py_ssize_t index, Py_ssize_t * value)
{
  return item_value(PyTuple_GET_ITEM(op, index), value);
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

// The kinds of a slot program (rosidl_buffer_py/codec/plans.py, slot_program; test_codec.py
// pins the numbers). A program is (class, check_fields, ((slot, kind, arg), ...)).
enum SlotKind : long
{
  kBool = 0, kInt8, kUint8, kInt16, kUint16, kInt32, kUint32, kInt64, kUint64, kFloat32,
  kFloat64, kStringSlot, kMessage, kPayload
};

/// The `size`-byte little- or big-endian value at the `size`-aligned position at or after
/// `*pos` (XCDR1 aligns every primitive to its size); false when it does not fit.
bool primitive(const Reader & r, size_t * pos, size_t size, uint64_t * value)
{
  const size_t start = (*pos + size - 1) & ~(size - 1);
  if (start > r.end || r.end - start < size) {
    return false;
  }
  uint64_t v = 0;
  for (size_t k = 0; k < size; ++k) {
    v |= uint64_t(r.body[start + k]) << (8 * (r.little ? k : size - 1 - k));
  }
  *value = v;
  *pos = start + size;
  return true;
}

/// One field's value as convert_to_py makes it, or nullptr (an exception may be set): a value
/// the generated code would treat otherwise (a bool byte other than 0 or 1, a string that is
/// not NUL-terminated UTF-8 without inner NULs or is over its bound) or that runs past the end
/// leaves the message to the generated code.
PyObject * build(PyObject * program, const Reader & r, size_t * pos, int depth);

PyObject * field_value(long kind, PyObject * arg, const Reader & r, size_t * pos, int depth)
{
  static const size_t sizes[] = {1, 1, 1, 2, 2, 4, 4, 8, 8, 4, 8};
  uint64_t v = 0;
  if (kind >= kBool && kind <= kFloat64) {
    if (!primitive(r, pos, sizes[kind], &v)) {
      return nullptr;
    }
  }
  switch (kind) {
    case kBool:
      return v > 1 ? nullptr : PyBool_FromLong(static_cast<long>(v));
    case kInt8: return PyLong_FromLong(static_cast<int8_t>(v));
    case kUint8: return PyLong_FromUnsignedLong(static_cast<uint8_t>(v));
    case kInt16: return PyLong_FromLong(static_cast<int16_t>(v));
    case kUint16: return PyLong_FromUnsignedLong(static_cast<uint16_t>(v));
    case kInt32: return PyLong_FromLong(static_cast<int32_t>(v));
    case kUint32: return PyLong_FromUnsignedLong(static_cast<uint32_t>(v));
    case kInt64: return PyLong_FromLongLong(static_cast<int64_t>(v));
    case kUint64: return PyLong_FromUnsignedLongLong(v);
    case kFloat32: {
        const uint32_t bits = static_cast<uint32_t>(v);
        float f;
        std::memcpy(&f, &bits, sizeof f);
        return PyFloat_FromDouble(f);
      }
    case kFloat64: {
        double d;
        std::memcpy(&d, &v, sizeof d);
        return PyFloat_FromDouble(d);
      }
    case kStringSlot: {
        uint32_t length;
        Py_ssize_t bound;
        if (!r.u32(pos, &length) || length < 1 || length > r.end - *pos ||
          r.body[*pos + length - 1] != 0 ||
          std::memchr(r.body + *pos, 0, length - 1) != nullptr ||
          !item_value(arg, &bound) || (bound >= 0 && length - 1 > static_cast<size_t>(bound)))
        {
          return nullptr;
        }
        PyObject * text = PyUnicode_DecodeUTF8(
          reinterpret_cast<const char *>(r.body + *pos), length - 1, "strict");
        *pos += length;
        return text;
      }
    case kMessage:
      return build(arg, r, pos, depth + 1);
    case kPayload: {
        uint32_t length;
        if (!r.u32(pos, &length) || length > r.end - *pos) {
          return nullptr;
        }
        PyObject * payload = PyObject_CallNoArgs(arg);
        if (payload != nullptr && length > 0) {  // one copy, where convert_to_py makes two
          PyObject * view = PyMemoryView_FromMemory(
            const_cast<char *>(reinterpret_cast<const char *>(r.body + *pos)), length, PyBUF_READ);
          PyObject * done = view ? PyObject_CallMethod(payload, "frombytes", "O", view) : nullptr;
          Py_XDECREF(view);
          if (done == nullptr) {
            Py_CLEAR(payload);
          }
          Py_XDECREF(done);
        }
        *pos += length;
        return payload;
      }
    default:
      return nullptr;
  }
}

PyObject * build(PyObject * program, const Reader & r, size_t * pos, int depth)
{
  if (depth > 64 || !PyTuple_Check(program) || PyTuple_GET_SIZE(program) != 3 ||
    !PyType_Check(PyTuple_GET_ITEM(program, 0)) || !PyTuple_Check(PyTuple_GET_ITEM(program, 2)))
  {
    return nullptr;
  }
  auto * type = reinterpret_cast<PyTypeObject *>(PyTuple_GET_ITEM(program, 0));
  PyObject * fields = PyTuple_GET_ITEM(program, 2);
  PyObject * no_args = PyTuple_New(0);
  PyObject * msg = no_args ? type->tp_new(type, no_args, nullptr) : nullptr;
  Py_XDECREF(no_args);
  if (msg == nullptr) {
    return nullptr;
  }
  static PyObject * check_slot = PyUnicode_InternFromString("_check_fields");
  if (check_slot == nullptr ||
    PyObject_SetAttr(msg, check_slot, PyTuple_GET_ITEM(program, 1)) < 0)
  {
    Py_DECREF(msg);
    return nullptr;
  }
  for (Py_ssize_t i = 0; i < PyTuple_GET_SIZE(fields); ++i) {
    PyObject * field = PyTuple_GET_ITEM(fields, i);
    Py_ssize_t kind;
    if (!PyTuple_Check(field) || PyTuple_GET_SIZE(field) != 3 || !item(field, 1, &kind)) {
      Py_DECREF(msg);
      return nullptr;
    }
    PyObject * value = field_value(kind, PyTuple_GET_ITEM(field, 2), r, pos, depth);
    if (value == nullptr || PyObject_SetAttr(msg, PyTuple_GET_ITEM(field, 0), value) < 0) {
      Py_XDECREF(value);
      Py_DECREF(msg);
      return nullptr;
    }
    Py_DECREF(value);
  }
  return msg;
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

/// CDR (XCDR1, this machine's byte order) written from a message's slots.
struct Writer
{
  std::vector<char> out{0, kLittleHost ? 1 : 0, 0, 0};  // the encapsulation header
  /// Whether a field of variable size (a string, the payload) was written: a message without
  /// one is fixed-size, and rmw_fastrtps sizes those to a multiple of 4 (codec: TypeCodec.plain).
  bool variable = false;

  void align(size_t n) {out.resize(out.size() + ((n - (out.size() - kHeader) % n) % n), '\0');}
  void put(uint64_t value, size_t size)
  {
    align(size);
    char b[8];
    for (size_t k = 0; k < size; ++k) {
      b[kLittleHost ? k : size - 1 - k] = static_cast<char>((value >> (8 * k)) & 0xFF);
    }
    out.insert(out.end(), b, b + size);
  }
  void bytes(const char * data, size_t size) {out.insert(out.end(), data, data + size);}
};

/// An exact int in [low, high] as its two's complement bits; false for anything else.
bool int_bits(PyObject * value, long long low, unsigned long long high, uint64_t * bits)
{
  if (!PyLong_CheckExact(value)) {
    return false;
  }
  int overflow = 0;
  const long long v = PyLong_AsLongLongAndOverflow(value, &overflow);
  if (overflow == 0 && v == -1 && PyErr_Occurred()) {
    return false;
  }
  if (overflow < 0) {
    return false;
  }
  if (overflow > 0) {  // above LLONG_MAX: only a uint64 takes it
    const unsigned long long u = PyLong_AsUnsignedLongLong(value);
    if (u == static_cast<unsigned long long>(-1) && PyErr_Occurred()) {
      return false;
    }
    if (u > high) {
      return false;
    }
    *bits = u;
    return true;
  }
  if (v < low || (v > 0 && static_cast<unsigned long long>(v) > high)) {
    return false;
  }
  *bits = static_cast<uint64_t>(v);
  return true;
}

struct DescriptorPart
{
  const char * backend;
  Py_ssize_t backend_length;
  const char * descriptor;
  Py_ssize_t descriptor_length;
};

/// The payload field as its descriptor: the marker, the backend's name, the descriptor.
bool write_descriptor(Writer * w, const DescriptorPart & part)
{
  w->variable = true;
  w->put(kMarker, 4);
  w->put(static_cast<uint32_t>(part.backend_length + 1), 4);
  w->bytes(part.backend, part.backend_length);
  w->out.push_back('\0');
  w->put(static_cast<uint32_t>(part.descriptor_length), 4);
  w->bytes(part.descriptor, part.descriptor_length);
  return true;
}

/// The payload field's own bytes, as convert_from_py copies any buffer-protocol object; false
/// for anything else (a list of ints: the generated code iterates it).
bool write_payload(Writer * w, PyObject * msg, PyObject * field)
{
  PyObject * value = PyObject_GetAttr(msg, PyTuple_GET_ITEM(field, 0));
  BufferView bytes;
  const bool ok = value != nullptr && PyObject_CheckBuffer(value) && bytes.get(value) &&
    bytes.size() <= UINT32_MAX;
  if (ok) {
    w->variable = true;
    w->put(static_cast<uint32_t>(bytes.size()), 4);
    w->bytes(reinterpret_cast<const char *>(bytes.data()), bytes.size());
  }
  Py_XDECREF(value);
  return ok;
}

/// `msg`'s fields written as the type support serializes what convert_from_py makes of them,
/// its payload as `part`'s descriptor when given, else as its bytes; false (an exception may be
/// set) for anything the program does not write
/// exactly so: a value not of the field's exact Python type, out of its range, a string with a
/// NUL or over its bound. encode_descriptor then takes the type support's path.
bool write_fields(PyObject * msg, PyObject * program, Writer * w, const DescriptorPart * part,
  int depth)
{
  if (depth > 64 || !PyTuple_Check(program) || PyTuple_GET_SIZE(program) != 3 ||
    reinterpret_cast<PyObject *>(Py_TYPE(msg)) != PyTuple_GET_ITEM(program, 0) ||
    !PyTuple_Check(PyTuple_GET_ITEM(program, 2)))
  {
    return false;
  }
  static const size_t sizes[] = {1, 1, 1, 2, 2, 4, 4, 8, 8, 4, 8};
  static const long long lows[] = {0, INT8_MIN, 0, INT16_MIN, 0, INT32_MIN, 0, INT64_MIN, 0};
  static const unsigned long long highs[] = {
    1, INT8_MAX, UINT8_MAX, INT16_MAX, UINT16_MAX, INT32_MAX, UINT32_MAX, INT64_MAX, UINT64_MAX};
  PyObject * fields = PyTuple_GET_ITEM(program, 2);
  for (Py_ssize_t i = 0; i < PyTuple_GET_SIZE(fields); ++i) {
    PyObject * field = PyTuple_GET_ITEM(fields, i);
    Py_ssize_t kind;
    if (!PyTuple_Check(field) || PyTuple_GET_SIZE(field) != 3 || !item(field, 1, &kind)) {
      return false;
    }
    if (kind == kPayload) {  // top level only: slot_program puts it nowhere else
      if (depth > 0 || !(part ? write_descriptor(w, *part) : write_payload(w, msg, field))) {
        return false;
      }
      part = nullptr;  // one payload
      continue;
    }
    PyObject * value = PyObject_GetAttr(msg, PyTuple_GET_ITEM(field, 0));
    if (value == nullptr) {
      return false;
    }
    bool ok = true;
    uint64_t bits = 0;
    if (kind == kBool) {
      ok = PyBool_Check(value);
      if (ok) {
        w->put(value == Py_True ? 1 : 0, 1);
      }
    } else if (kind >= kInt8 && kind <= kUint64) {
      ok = int_bits(value, lows[kind], highs[kind], &bits);
      if (ok) {
        w->put(bits, sizes[kind]);
      }
    } else if (kind == kFloat32 || kind == kFloat64) {
      ok = PyFloat_CheckExact(value);
      if (ok && kind == kFloat32) {
        const float f = static_cast<float>(PyFloat_AS_DOUBLE(value));
        uint32_t b32;
        std::memcpy(&b32, &f, sizeof b32);
        w->put(b32, 4);
      } else if (ok) {
        const double d = PyFloat_AS_DOUBLE(value);
        std::memcpy(&bits, &d, sizeof bits);
        w->put(bits, 8);
      }
    } else if (kind == kStringSlot) {
      Py_ssize_t length = 0;
      Py_ssize_t bound;
      const char * text = PyUnicode_CheckExact(value) ?
        PyUnicode_AsUTF8AndSize(value, &length) : nullptr;
      ok = text != nullptr && std::memchr(text, 0, static_cast<size_t>(length)) == nullptr &&
        item_value(PyTuple_GET_ITEM(field, 2), &bound) && (bound < 0 || length <= bound);
      if (ok) {
        w->put(static_cast<uint32_t>(length + 1), 4);
        w->bytes(text, static_cast<size_t>(length));
        w->out.push_back('\0');
        w->variable = true;
      }
    } else if (kind == kMessage) {
      ok = write_fields(value, PyTuple_GET_ITEM(field, 2), w, nullptr, depth + 1);
    } else {
      ok = false;
    }
    Py_DECREF(value);
    if (!ok) {
      return false;
    }
  }
  return part == nullptr || depth > 0;  // a descriptor asked for is written
}

/// `msg`'s CDR written by `program` into `out`, the payload as `part`'s descriptor when given;
/// a fixed-size message padded to a multiple of 4, as rmw_fastrtps sizes it (codec:
/// TypeCodec.plain). False, no exception set, when the program is None or cannot write it.
bool write_cdr(PyObject * msg, PyObject * program, const DescriptorPart * part,
  std::vector<char> * out)
{
  if (program == nullptr || program == Py_None) {
    return false;
  }
  Writer w;
  if (!write_fields(msg, program, &w, part, 0)) {
    PyErr_Clear();
    return false;
  }
  if (!w.variable) {
    w.align(4);
  }
  *out = std::move(w.out);
  return true;
}

/// None, after clearing any pending exception: the Python codec takes over.
PyObject * fall_back()
{
  PyErr_Clear();
  Py_RETURN_NONE;
}


/// The message `program` builds from CDR with its encapsulation header; nullptr, no exception
/// set, when it cannot, or (`whole`) when it leaves bytes unread. Bytes after the last field are
/// otherwise ignored, as the type support's deserialization ignores them.
PyObject * build_message(PyObject * program, const uint8_t * data, size_t length, bool whole)
{
  if (program == nullptr || program == Py_None || length < kHeader || data[0] != 0 ||
    data[1] > 1)
  {
    return nullptr;
  }
  Reader r{data + kHeader, length - kHeader, data[1] == 1};
  size_t pos = 0;
  PyObject * msg = build(program, r, &pos, 0);
  if (msg != nullptr && whole && pos != r.end) {
    Py_CLEAR(msg);
  }
  PyErr_Clear();
  return msg;
}

/// `small` deserialized by the type support and converted by the generated convert_to_py, as
/// deserialize_message does; nullptr when it cannot.
PyObject * converted(PyObject * msg_class, const std::vector<uint8_t> & small)
{
  MessageSupport support;
  if (support.load(msg_class) < 0) {
    return nullptr;
  }
  rmw_serialized_message_t serialized = rmw_get_zero_initialized_serialized_message();
  serialized.buffer = const_cast<uint8_t *>(small.data());
  serialized.buffer_length = serialized.buffer_capacity = small.size();
  OwnedRosMessage ros_message(&support);
  if (!try_deserialize(support, serialized, &ros_message)) {
    return nullptr;
  }
  return support.to_py(ros_message.get());
}

/// nullptr after clearing any pending exception: not a descriptor message (decode_described).
PyObject * no_descriptor()
{
  PyErr_Clear();
  return nullptr;
}

}  // namespace

PyObject * decode_described(
  const uint8_t * data, size_t size, PyObject * msg_class, PyObject * ops,
  Py_ssize_t suffix_size, Py_ssize_t max_descriptor, PyObject * program)
{
  if (size < kHeader || suffix_size < 0 || !PyTuple_Check(ops)) {
    return no_descriptor();
  }
  if (data[0] != 0 || data[1] > 1) {
    return no_descriptor();  // not XCDR1: the codec names the encapsulation
  }
  if (data[2] != 0 || data[3] != 0) {
    // options the codec never writes: a channel's control message ('RB', rosidl_buffer_py
    // /control.py) is never read as a descriptor message, whatever its value bytes hold
    return no_descriptor();
  }
  Reader r{data + kHeader, size - kHeader, data[1] == 1};
  size_t pos = 0;
  uint32_t first;
  if (!walk(ops, r, &pos, 0) || !r.u32(&pos, &first) || first != kMarker) {
    return no_descriptor();  // CPU bytes (or malformed): the codec's path
  }
  const size_t head_end = kHeader + pos - 4;
  uint32_t length;
  if (!r.u32(&pos, &length) || length < 2 || length > r.end - pos ||
    r.body[pos + length - 1] != 0 ||
    std::memchr(r.body + pos, 0, length - 1) != nullptr)
  {
    return no_descriptor();
  }
  const char * name = reinterpret_cast<const char *>(r.body + pos);
  const Py_ssize_t name_length = static_cast<Py_ssize_t>(length - 1);
  pos += length;
  uint32_t nbytes;
  if (!r.u32(&pos, &nbytes) || nbytes > static_cast<uint64_t>(max_descriptor) ||
    nbytes > r.end - pos)
  {
    return no_descriptor();
  }
  const uint8_t * descriptor = r.body + pos;
  const size_t data_end = pos + nbytes;
  if (static_cast<size_t>(suffix_size) > r.end - data_end) {
    return no_descriptor();
  }
  // The message without its payload: the head, a zero length, the fields after the payload.
  std::vector<uint8_t> small(head_end + 4 + suffix_size);
  std::memcpy(small.data(), data, head_end);
  std::memset(small.data() + head_end, 0, 4);
  std::memcpy(small.data() + head_end + 4, r.body + data_end, suffix_size);
  PyObject * msg = build_message(program, small.data(), small.size(), true);
  if (msg == nullptr) {  // no program, or a value it leaves to the generated code
    msg = converted(msg_class, small);
    if (msg == nullptr) {
      return no_descriptor();
    }
  }
  PyObject * backend = PyUnicode_DecodeUTF8(name, name_length, "strict");
  PyObject * desc = backend ? PyBytes_FromStringAndSize(
    reinterpret_cast<const char *>(descriptor), nbytes) : nullptr;
  PyObject * result = desc ? PyTuple_Pack(3, msg, backend, desc) : nullptr;
  Py_DECREF(msg);
  Py_XDECREF(backend);
  Py_XDECREF(desc);
  return result ? result : no_descriptor();
}

namespace
{

PyObject * decode_descriptor(PyObject *, PyObject * args)
{
  PyObject * raw;
  PyObject * msg_class;
  PyObject * ops;
  Py_ssize_t suffix_size;
  Py_ssize_t max_descriptor;
  PyObject * program = Py_None;
  if (!PyArg_ParseTuple(
      args, "OOO!nn|O:decode_descriptor", &raw, &msg_class, &PyTuple_Type, &ops, &suffix_size,
      &max_descriptor, &program))
  {
    return nullptr;
  }
  BufferView input;
  if (!input.get(raw)) {
    return fall_back();
  }
  PyObject * result = decode_described(
    input.data(), input.size(), msg_class, ops, suffix_size, max_descriptor, program);
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
  PyObject * program = Py_None;
  if (!PyArg_ParseTuple(
      args, "OO!UOy#y#n|O:encode_descriptor", &msg, &PyTuple_Type, &slots, &payload_slot,
      &empty, &backend, &backend_length, &descriptor, &descriptor_length, &suffix_size,
      &program))
  {
    return nullptr;
  }
  if (suffix_size < 0) {
    return fall_back();
  }
  const DescriptorPart part{backend, backend_length, descriptor, descriptor_length};
  if (program != Py_None) {  // the slots written directly, where the program can
    std::vector<char> out;
    if (write_cdr(msg, program, &part, &out)) {
      return PyByteArray_FromStringAndSize(out.data(), static_cast<Py_ssize_t>(out.size()));
    }
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
  // (DEFAULT_ENDIAN is this machine's byte order, the Writer's)
  if (length > buffer.size() || length < kHeader + 4 + static_cast<size_t>(suffix_size) ||
    bytes[0] != 0 || bytes[1] != (kLittleHost ? 1 : 0))
  {
    return fall_back();
  }
  const size_t at = length - suffix_size - 4;
  if ((at - kHeader) % 4 != 0 || std::memcmp(bytes + at, "\0\0\0\0", 4) != 0) {
    return fall_back();
  }
  Writer w;
  w.out.assign(buffer.data(), buffer.data() + at);
  write_descriptor(&w, part);
  w.bytes(buffer.data() + at + 4, suffix_size);
  return PyByteArray_FromStringAndSize(w.out.data(), static_cast<Py_ssize_t>(w.out.size()));
}

/// deserialize(raw, program) -> message | None: CDR built by a slot program.
PyObject * deserialize(PyObject *, PyObject * args)
{
  PyObject * raw;
  PyObject * program;
  if (!PyArg_ParseTuple(args, "OO:deserialize", &raw, &program)) {
    return nullptr;
  }
  BufferView input;
  if (!input.get(raw)) {
    return fall_back();
  }
  PyObject * msg = build_from_cdr(program, input.data(), input.size());
  return msg ? msg : fall_back();
}

/// serialize(msg, program) -> bytearray | None: CDR written from the slots.
PyObject * serialize(PyObject *, PyObject * args)
{
  PyObject * msg;
  PyObject * program;
  if (!PyArg_ParseTuple(args, "OO:serialize", &msg, &program)) {
    return nullptr;
  }
  std::vector<char> out;
  if (!write_from_slots(msg, program, &out)) {
    return fall_back();
  }
  return PyByteArray_FromStringAndSize(out.data(), static_cast<Py_ssize_t>(out.size()));
}

}  // namespace

bool write_from_slots(PyObject * msg, PyObject * program, std::vector<char> * out)
{
  return write_cdr(msg, program, nullptr, out);
}

bool write_described_from_slots(
  PyObject * msg, PyObject * program, const char * backend, Py_ssize_t backend_length,
  const char * descriptor, Py_ssize_t descriptor_length, std::vector<char> * out)
{
  const DescriptorPart part{backend, backend_length, descriptor, descriptor_length};
  return write_cdr(msg, program, &part, out);
}

PyObject * build_from_cdr(PyObject * program, const uint8_t * data, size_t length)
{
  return build_message(program, data, length, false);
}

PyMethodDef codec_functions[] = {
  RBPY_FUNCTION(encode_descriptor, METH_VARARGS,
    "encode_descriptor(msg, slots, payload_slot, empty, backend, descriptor, suffix_size, "
    "program=None) -> bytearray | None\n\ncodec.encode(msg, (backend, descriptor)) of a plan "
    "(slots, payload slot, suffix size) in C: written from the slots by `program` (a slot "
    "program of codec/plans.py) where it can, otherwise a payload-free clone (holding `empty`) "
    "serialized by the type support. None when it cannot (the Python codec then raises the "
    "CodecError)."),
  RBPY_FUNCTION(decode_descriptor, METH_VARARGS,
    "decode_descriptor(raw, msg_class, prefix_ops, suffix_size, max_descriptor, program=None) "
    "-> (msg, backend_type, descriptor) | None\n\ncodec.decode() of descriptor-encoded CDR in "
    "C (the message's payload field left empty). The message is built by `program` (a slot "
    "program of codec/plans.py) where it can, otherwise by the type support, as "
    "deserialize_message. None for CPU bytes and anything malformed: the Python codec then "
    "decodes or rejects it."),
  RBPY_FUNCTION(serialize, METH_VARARGS,
    "serialize(msg, program) -> bytearray | None\n\nThe CDR of msg (encapsulation header, zero "
    "padding) written from its slots by a slot program of codec/plans.py: codec.encode(msg)'s "
    "bytes; None where the program cannot write them exactly as the type support would."),
  RBPY_FUNCTION(deserialize, METH_VARARGS,
    "deserialize(raw, program) -> message | None\n\nCDR (with its encapsulation header) "
    "built into a message by a slot program of codec/plans.py, the message deserialize_message "
    "gives; None when the program cannot build it exactly so (deserialize_message then does)."),
  RBPY_METHODS_END,
};

}  // namespace rbpy_dds
