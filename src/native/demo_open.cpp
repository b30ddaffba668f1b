// open_mapped: a demo descriptor taken, its segment's view opened, in one native call.
//
// A demo subscriber opens every descriptor it takes (demo_buffer_backend.mappings.Mappings),
// on cold caches at camera rates, where each Python line costs ten to thirty times its warm
// cost. This is that open for a well-formed descriptor of a segment that is mapped and
// current, as demo_buffer_backend/mappings.py describes it; anything else gets None and
// nothing changed, and the Python open then does the same and says why it fails (the pattern
// of codec_fast.cpp's decode_descriptor).
#include "demo_open.hpp"

#include <fcntl.h>

#include <cstdint>
#include <cstring>

#include "py_glue.hpp"

namespace
{

using rbpy_glue::int_attr;
using rbpy_glue::intern;
using rbpy_glue::set_attr;
using rbpy_glue::set_int_attr;

PyObject * s_retired, * s_received, * s_refs, * s_conn, * s_view, * s_capacity, * s_fd, * s_map;
PyObject * s_last_used, * s_taken;

// demo_buffer_backend/descriptor.py's layout '<4sBBHIQIIQQQ' (52 bytes): the 8-byte prefix
// (magic, version, reserved), pid u32, nonce u64, segment id u32, reserved u32, generation,
// offset, size (u64 each).
constexpr Py_ssize_t kDescriptorSize = 52;
constexpr Py_ssize_t kPrefixSize = 8;
// demo_buffer_backend/memory.py's HEADER '<8sQQQQ': magic, capacity, generation, offset, size.
constexpr Py_ssize_t kHeaderSize = 40;

template<typename T>
T read_le(const unsigned char * at)
{
  T value;
  std::memcpy(&value, at, sizeof(T));  // little-endian host (x86_64, aarch64)
  return value;
}

/// Copy a packed `struct flock` (bytes of exactly its size) into `out`.
bool flock_of(PyObject * packed, struct flock * out)
{
  char * data = nullptr;
  Py_ssize_t size = 0;
  if (PyBytes_AsStringAndSize(packed, &data, &size) < 0) {
    return false;
  }
  if (size != static_cast<Py_ssize_t>(sizeof(struct flock))) {
    PyErr_Format(PyExc_ValueError, "a packed struct flock has %zd bytes, got %zd",
      sizeof(struct flock), size);
    return false;
  }
  std::memcpy(out, data, sizeof(struct flock));
  return true;
}

/// The fields of a well-formed descriptor of this medium.
struct Descriptor
{
  uint32_t pid;
  uint64_t nonce;
  uint32_t segment_id;
  uint64_t generation, offset, size;
};

/// Parse `raw` (a bytes-like object): false when it is not a well-formed descriptor with
/// `prefix` (magic, version, zero reserved bytes). Never raises.
bool parse(PyObject * raw, PyObject * prefix, Descriptor * d)
{
  if (!PyObject_CheckBuffer(raw)) {
    return false;
  }
  Py_buffer view;
  if (PyObject_GetBuffer(raw, &view, PyBUF_SIMPLE) < 0) {
    PyErr_Clear();
    return false;
  }
  const auto * at = static_cast<const unsigned char *>(view.buf);
  bool ok = view.len == kDescriptorSize && PyBytes_GET_SIZE(prefix) == kPrefixSize &&
    std::memcmp(at, PyBytes_AS_STRING(prefix), kPrefixSize) == 0 &&
    read_le<uint32_t>(at + 24) == 0;
  if (ok) {
    *d = Descriptor{read_le<uint32_t>(at + 8), read_le<uint64_t>(at + 12),
      read_le<uint32_t>(at + 20), read_le<uint64_t>(at + 28), read_le<uint64_t>(at + 36),
      read_le<uint64_t>(at + 44)};
    ok = d->pid != 0 && d->generation != 0;  // neither is ever published
  }
  PyBuffer_Release(&view);
  return ok;
}

/// The segment header's (generation, offset, size) from its mapping; false with an exception
/// set on error.
bool header_of(PyObject * received, uint64_t * generation, uint64_t * offset, uint64_t * size)
{
  PyObject * map = PyObject_GetAttr(received, s_map);
  if (map == nullptr) {
    return false;
  }
  Py_buffer view;
  const bool got = PyObject_GetBuffer(map, &view, PyBUF_SIMPLE) == 0;
  Py_DECREF(map);
  if (!got) {
    return false;
  }
  const bool ok = view.len >= kHeaderSize;
  if (ok) {
    const auto * at = static_cast<const unsigned char *>(view.buf);
    *generation = read_le<uint64_t>(at + 16);
    *offset = read_le<uint64_t>(at + 24);
    *size = read_le<uint64_t>(at + 32);
  } else {
    PyErr_SetString(PyExc_ValueError, "a segment's mapping is shorter than its header");
  }
  PyBuffer_Release(&view);
  return ok;
}

// open_mapped(prefix, read_lock, unlock, counters, raw, by_key, unacked, now)
PyObject * open_mapped(PyObject *, PyObject * const * args, Py_ssize_t nargs)
{
  if (nargs != 8) {
    PyErr_Format(PyExc_TypeError, "open_mapped takes 8 arguments, got %zd", nargs);
    return nullptr;
  }
  PyObject * prefix = args[0], * read_lock = args[1], * unlock = args[2];
  PyObject * counters = args[3], * raw = args[4], * by_key = args[5], * unacked = args[6];
  PyObject * now = args[7];
  if (!PyBytes_Check(prefix) || !PyBytes_Check(read_lock) || !PyBytes_Check(unlock) ||
    !PyDict_Check(by_key) || !PyList_Check(unacked))
  {
    PyErr_SetString(
      PyExc_TypeError, "open_mapped(prefix: bytes, read_lock: bytes, unlock: bytes, counters, "
      "raw, by_key: dict, unacked: list, now)");
    return nullptr;
  }
  Descriptor d;
  if (!parse(raw, prefix, &d)) {
    Py_RETURN_NONE;
  }
  PyObject * key = Py_BuildValue("(kKk)", static_cast<unsigned long>(d.pid),
      static_cast<unsigned long long>(d.nonce), static_cast<unsigned long>(d.segment_id));
  if (key == nullptr) {
    return nullptr;
  }
  PyObject * mapping = PyDict_GetItemWithError(by_key, key);  // borrowed
  Py_DECREF(key);
  if (mapping == nullptr) {
    if (PyErr_Occurred()) {
      return nullptr;
    }
    Py_RETURN_NONE;  // not (yet) handed over: the Python open receives, or says why not
  }
  Py_INCREF(mapping);
  PyObject * received = nullptr, * conn = nullptr, * record = nullptr, * view = nullptr;
  PyObject * part = nullptr, * result = nullptr;
  struct flock lock_request, unlock_request;
  long long refs = 0, capacity = 0, fd = -1, taken = 0;
  uint64_t generation = 0, recorded_offset = 0, recorded_size = 0;
  bool locked = false;
  PyObject * retired = PyObject_GetAttr(mapping, s_retired);
  const int is_retired = retired ? PyObject_IsTrue(retired) : -1;
  Py_XDECREF(retired);
  if (is_retired != 0) {
    goto done;  // error, or retired: the Python open says why
  }
  received = PyObject_GetAttr(mapping, s_received);
  capacity = received ? int_attr(received, s_capacity) : -1;
  if (PyErr_Occurred() || d.offset > static_cast<uint64_t>(capacity) ||
    d.size > static_cast<uint64_t>(capacity) - d.offset)
  {
    goto done;
  }
  refs = int_attr(mapping, s_refs);
  if (PyErr_Occurred()) {
    goto done;
  }
  if (refs == 0) {  // the first hold takes the segment's shared lock
    fd = int_attr(received, s_fd);
    if (PyErr_Occurred() || !flock_of(read_lock, &lock_request) ||
      !flock_of(unlock, &unlock_request))
    {
      goto done;
    }
    if (fcntl(static_cast<int>(fd), F_OFD_SETLK, &lock_request) != 0) {
      goto done;  // its publisher holds it: the Python open waits a little, or says stale
    }
    locked = true;
  }
  if (!header_of(received, &generation, &recorded_offset, &recorded_size)) {
    goto done;
  }
  if (generation != d.generation || recorded_offset != d.offset || recorded_size != d.size) {
    goto done;  // stale, or not what its publisher recorded: the Python open says which
  }
  // what can fail first (the acknowledgment record, the view, the answer), then the take is
  // committed
  conn = PyObject_GetAttr(mapping, s_conn);
  if (conn != nullptr && conn != Py_None) {  // acknowledged once the view is let go
    record = Py_BuildValue("(Okk)", conn, static_cast<unsigned long>(d.segment_id),
        static_cast<unsigned long>(generation));
  }
  view = conn && (conn == Py_None || record) ? PyObject_GetAttr(mapping, s_view) : nullptr;
  part = view ? PySequence_GetSlice(view, static_cast<Py_ssize_t>(d.offset),
      static_cast<Py_ssize_t>(d.offset + d.size)) : nullptr;
  taken = part ? int_attr(counters, s_taken) : -1;
  result = part && !PyErr_Occurred() ?
    Py_BuildValue("(OOKO)", part, mapping, static_cast<unsigned long long>(generation),
      conn != Py_None ? Py_True : Py_False) : nullptr;
  if (result == nullptr || set_int_attr(mapping, s_refs, refs + 1) < 0) {
    Py_CLEAR(result);
    goto done;
  }
  locked = false;  // the hold owns the lock from here on
  if ((record != nullptr && PyList_Append(unacked, record) < 0) ||
    set_attr(mapping, s_last_used, Py_NewRef(now)) < 0 ||
    set_int_attr(counters, s_taken, taken + 1) < 0)
  {
    // (memory errors only) undo the hold, as the Python open's release would
    set_int_attr(mapping, s_refs, refs);
    locked = refs == 0;
    Py_CLEAR(result);
  }

done:
  if (locked) {  // nothing opened: the lock goes as it came (errors kept as they are)
    rbpy_glue::SavedException saved;
    fcntl(static_cast<int>(fd), F_OFD_SETLK, &unlock_request);
  }
  Py_XDECREF(part);
  Py_XDECREF(view);
  Py_XDECREF(record);
  Py_XDECREF(conn);
  Py_XDECREF(received);
  Py_DECREF(mapping);
  if (result == nullptr && !PyErr_Occurred()) {
    Py_RETURN_NONE;
  }
  return result;
}

PyMethodDef open_functions[] = {
  {"open_mapped", reinterpret_cast<PyCFunction>(reinterpret_cast<void (*)(void)>(open_mapped)),
    METH_FASTCALL,
    "open_mapped(prefix, read_lock, unlock, counters, raw, by_key, unacked, now)\n--\n\n"
    "The demo descriptor `raw` opened: (view, mapping, generation, acknowledged later) for a "
    "well-formed descriptor (its first 8 bytes `prefix`) of a segment in `by_key` that is "
    "current, its range the one recorded, its shared lock taken with `read_lock` (a packed "
    "struct flock) when it holds none; its take appended to `unacked` when the mapping has a "
    "connection, its refs, last_used and counters.taken updated. None, with nothing changed, "
    "for anything else."},
  RBPY_METHODS_END,
};

}  // namespace

int add_demo_open(PyObject * module)
{
  if (!intern(&s_retired, "retired") || !intern(&s_received, "received") ||
    !intern(&s_refs, "refs") || !intern(&s_conn, "conn") || !intern(&s_view, "view") ||
    !intern(&s_capacity, "capacity") || !intern(&s_fd, "fd") || !intern(&s_map, "map") ||
    !intern(&s_last_used, "last_used") || !intern(&s_taken, "taken"))
  {
    return -1;
  }
  return PyModule_AddFunctions(module, open_functions);
}
