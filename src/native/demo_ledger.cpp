// LedgerCore: the rules of the demo backend's per-endpoint ledgers, run natively.
//
// demo_buffer_backend/ledgers.py documents the rules (what an endpoint gives up, when it is
// full); its EndpointLedger is a thin subclass of this type. These rules run for every
// descriptor a publisher describes, on cold caches at camera rates, where each Python line
// costs ten to thirty times its warm cost: here they cost one native call each.
//
// The state the rules read lives where it did: each slot's `closed`, `generation`,
// `capacity` and its per-token `sent`, `taken` and `released` counts (Python dicts on
// demo_buffer_backend.slots.Slot), the pool's counters, and the share of the pool an endpoint
// may hold, which the subclass's `_share(history_known, depth)` computes (from the limits
// object given at construction) and this type caches while those limits hold.
#include "demo_ledger.hpp"

#include <structmember.h>

#include <deque>
#include <new>

#include "py_glue.hpp"

namespace
{

using rbpy_glue::add_counter;
using rbpy_glue::int_attr;
using rbpy_glue::intern;

// Attribute names, interned once.
PyObject * s_closed, * s_generation, * s_capacity, * s_sent, * s_taken, * s_released;
PyObject * s_released_skipped, * s_released_window, * s_released_share;
PyObject * s_max_inflight_per_peer, * s_max_slots, * s_max_pool_bytes;

struct Entry
{
  PyObject * slot;  // owned
  long long generation;
  long long seq;
};

/// The share of the pool an endpoint may hold, for one value of what it depends on.
struct Share
{
  bool valid = false;
  long long depth = 0, max_inflight_per_peer = 0, max_slots = 0, max_pool_bytes = 0;
  long long count = 0, nbytes = 0;
};

struct LedgerObject
{
  PyObject_HEAD
  PyObject * token;  // str
  PyObject * depth;  // None or int
  PyObject * delivered;  // None or a callable
  PyObject * limits;  // read for the share's cache key
  long long seq;
  int per_channel;
  std::deque<Entry> * inflight;
  Share shares[2];  // by history known
};

LedgerObject * as_ledger(PyObject * self) {return reinterpret_cast<LedgerObject *>(self);}

/// `obj.name`, which must be a dict (a new reference), or nullptr with an exception set.
PyObject * counts_of(PyObject * obj, PyObject * name)
{
  PyObject * counts = PyObject_GetAttr(obj, name);
  if (counts != nullptr && !PyDict_Check(counts)) {
    PyErr_Format(PyExc_TypeError, "slot.%U must be a dict, got %.100s", name,
      Py_TYPE(counts)->tp_name);
    Py_CLEAR(counts);
  }
  return counts;
}

/// `counts[key]` of a dict of ints, 0 when absent; -1 with an exception set on error.
long long count_in(PyObject * counts, PyObject * key)
{
  PyObject * value = PyDict_GetItemWithError(counts, key);
  if (value == nullptr) {
    return PyErr_Occurred() ? -1 : 0;
  }
  return PyLong_AsLongLong(value);
}

/// `obj.name[key]` of a dict of ints, 0 when absent; -1 with an exception set on error.
long long count_of(PyObject * obj, PyObject * name, PyObject * key)
{
  PyObject * counts = counts_of(obj, name);
  if (counts == nullptr) {
    return -1;
  }
  const long long result = count_in(counts, key);
  Py_DECREF(counts);
  return result;
}

/// Add `delta` to `obj.name[key]` (a dict of ints). 0, or -1 with an exception set.
int add_count(PyObject * obj, PyObject * name, PyObject * key, long long delta)
{
  PyObject * counts = counts_of(obj, name);
  if (counts == nullptr) {
    return -1;
  }
  const long long now = count_in(counts, key);
  PyObject * value = now == -1 && PyErr_Occurred() ? nullptr : PyLong_FromLongLong(now + delta);
  const int result = value ? PyDict_SetItem(counts, key, value) : -1;
  Py_XDECREF(value);
  Py_DECREF(counts);
  return result;
}

/// Whether the entry's slot still holds the entry's generation (not reused, not removed):
/// 1, 0, or -1 with an exception set.
int current(const Entry & entry)
{
  PyObject * closed = PyObject_GetAttr(entry.slot, s_closed);
  if (closed == nullptr) {
    return -1;
  }
  const int is_closed = PyObject_IsTrue(closed);
  Py_DECREF(closed);
  if (is_closed != 0) {
    return is_closed < 0 ? -1 : 0;
  }
  const long long generation = int_attr(entry.slot, s_generation);
  if (generation == -1 && PyErr_Occurred()) {
    return -1;
  }
  return generation == entry.generation ? 1 : 0;
}

/// Whether the endpoint took or gave up every descriptor of the slot's generation: 1, 0, or
/// -1 with an exception set.
int settled(PyObject * slot, PyObject * token)
{
  const long long taken = count_of(slot, s_taken, token);
  const long long released = taken == -1 && PyErr_Occurred() ? -1 :
    count_of(slot, s_released, token);
  const long long sent = released == -1 && PyErr_Occurred() ? -1 :
    count_of(slot, s_sent, token);
  if (sent == -1 && PyErr_Occurred()) {
    return -1;
  }
  return taken + released >= sent ? 1 : 0;
}

/// Stop `entry` pinning its slot: 1 when given up, 0 when the slot moved on meanwhile, -1 with
/// an exception set.
int give_up(LedgerObject * ledger, const Entry & entry)
{
  const int is_current = current(entry);
  if (is_current <= 0) {
    return is_current;
  }
  return add_count(entry.slot, s_released, ledger->token, 1) < 0 ? -1 : 1;
}

void drop(Entry & entry) {Py_CLEAR(entry.slot);}

/// Give up the oldest entry and remove it, adding 1 to `*given` when it still pinned its slot.
/// False with an exception set on error (the entry then stays).
bool give_up_oldest(LedgerObject * ledger, long long * given)
{
  Entry entry = ledger->inflight->front();
  const int result = give_up(ledger, entry);
  if (result < 0) {
    return false;
  }
  ledger->inflight->pop_front();
  drop(entry);
  *given += result;
  return true;
}

/// The share (descriptors, bytes) for `history_known` and `depth`: cached while the limits
/// it depends on hold, else the subclass's `_share(history_known, depth)`. False with an
/// exception set on error.
bool share_of(LedgerObject * ledger, bool history_known, long long depth, Share ** found)
{
  Share & share = ledger->shares[history_known ? 1 : 0];
  const long long max_inflight = int_attr(ledger->limits, s_max_inflight_per_peer);
  const long long max_slots = PyErr_Occurred() ? -1 : int_attr(ledger->limits, s_max_slots);
  const long long max_bytes = PyErr_Occurred() ? -1 :
    int_attr(ledger->limits, s_max_pool_bytes);
  if (PyErr_Occurred()) {
    return false;
  }
  if (!share.valid || share.depth != depth || share.max_inflight_per_peer != max_inflight ||
    share.max_slots != max_slots || share.max_pool_bytes != max_bytes)
  {
    PyObject * result = PyObject_CallMethod(
      reinterpret_cast<PyObject *>(ledger), "_share", "OL",
      history_known ? Py_True : Py_False, depth);
    if (result == nullptr) {
      return false;
    }
    long long count = 0, nbytes = 0;
    const bool ok = PyArg_ParseTuple(result, "LL;_share must return (count, bytes)", &count,
        &nbytes);
    Py_DECREF(result);
    if (!ok) {
      return false;
    }
    share = Share{true, depth, max_inflight, max_slots, max_bytes, count, nbytes};
  }
  *found = &share;
  return true;
}

/// Whether the in-flight list holds the endpoint's share (descriptors or bytes): 1, 0, or -1
/// with an exception set.
int past_share(LedgerObject * ledger, bool history_known, long long depth)
{
  Share * share = nullptr;
  if (!share_of(ledger, history_known, depth, &share)) {
    return -1;
  }
  const auto & inflight = *ledger->inflight;
  if (static_cast<long long>(inflight.size()) >= share->count) {
    return 1;
  }
  long long pinned = 0;
  for (const Entry & entry : inflight) {
    const long long capacity = int_attr(entry.slot, s_capacity);
    if (capacity == -1 && PyErr_Occurred()) {
      return -1;
    }
    pinned += capacity;
  }
  return pinned >= share->nbytes ? 1 : 0;
}

/// The ledger's depth as a number: its KEEP_LAST depth, 0 for KEEP_ALL; `known` false when
/// None. False with an exception set on error.
bool depth_of(LedgerObject * ledger, long long * depth, bool * known)
{
  *known = ledger->depth != Py_None;
  *depth = 0;
  if (*known) {
    *depth = PyLong_AsLongLong(ledger->depth);
    if (*depth == -1 && PyErr_Occurred()) {
      return false;
    }
  }
  return true;
}

// --- the type -------------------------------------------------------------------------------

int ledger_init(PyObject * self, PyObject * args, PyObject * kwds)
{
  static const char * kwlist[] = {"token", "depth", "per_channel", "delivered", "limits",
    nullptr};
  PyObject * token = nullptr, * depth = Py_None, * delivered = Py_None, * limits = nullptr;
  int per_channel = 1;
  if (!PyArg_ParseTupleAndKeywords(
      args, kwds, "UOpOO:LedgerCore", const_cast<char **>(kwlist), &token, &depth,
      &per_channel, &delivered, &limits))
  {
    return -1;
  }
  auto * ledger = as_ledger(self);
  if (ledger->inflight != nullptr) {
    PyErr_SetString(PyExc_RuntimeError, "LedgerCore is already initialized");
    return -1;
  }
  ledger->inflight = new (std::nothrow) std::deque<Entry>();
  if (ledger->inflight == nullptr) {
    PyErr_NoMemory();
    return -1;
  }
  Py_XSETREF(ledger->token, Py_NewRef(token));
  Py_XSETREF(ledger->depth, Py_NewRef(depth));
  Py_XSETREF(ledger->delivered, Py_NewRef(delivered));
  Py_XSETREF(ledger->limits, Py_NewRef(limits));
  ledger->per_channel = per_channel;
  ledger->seq = 0;
  return 0;
}

void clear_inflight(LedgerObject * ledger)
{
  if (ledger->inflight != nullptr) {
    for (Entry & entry : *ledger->inflight) {
      drop(entry);
    }
    ledger->inflight->clear();
  }
}

int ledger_traverse(PyObject * self, visitproc visit, void * arg)
{
  auto * ledger = as_ledger(self);
  Py_VISIT(ledger->token);
  Py_VISIT(ledger->depth);
  Py_VISIT(ledger->delivered);
  Py_VISIT(ledger->limits);
  if (ledger->inflight != nullptr) {
    for (const Entry & entry : *ledger->inflight) {
      Py_VISIT(entry.slot);
    }
  }
  Py_VISIT(Py_TYPE(self));
  return 0;
}

int ledger_clear(PyObject * self)
{
  auto * ledger = as_ledger(self);
  Py_CLEAR(ledger->token);
  Py_CLEAR(ledger->depth);
  Py_CLEAR(ledger->delivered);
  Py_CLEAR(ledger->limits);
  clear_inflight(ledger);
  return 0;
}

void ledger_dealloc(PyObject * self)
{
  PyTypeObject * tp = Py_TYPE(self);
  PyObject_GC_UnTrack(self);
  ledger_clear(self);
  delete as_ledger(self)->inflight;
  as_ledger(self)->inflight = nullptr;
  tp->tp_free(self);
  Py_DECREF(tp);
}

bool ready(LedgerObject * ledger)
{
  if (ledger->inflight == nullptr || ledger->token == nullptr) {
    PyErr_SetString(PyExc_RuntimeError, "LedgerCore.__init__ was not called");
    return false;
  }
  return true;
}

PyObject * ledger_record(PyObject * self, PyObject * slot)
{
  auto * ledger = as_ledger(self);
  if (!ready(ledger)) {
    return nullptr;
  }
  const long long generation = int_attr(slot, s_generation);
  if ((generation == -1 && PyErr_Occurred()) ||
    add_count(slot, s_sent, ledger->token, 1) < 0)
  {
    return nullptr;
  }
  ledger->inflight->push_back(Entry{Py_NewRef(slot), generation, ledger->seq});
  Py_RETURN_NONE;
}

PyObject * ledger_settle(PyObject * self, PyObject * counters)
{
  auto * ledger = as_ledger(self);
  if (!ready(ledger)) {
    return nullptr;
  }
  auto & inflight = *ledger->inflight;
  if (inflight.empty()) {  // nothing to settle (an endpoint that keeps up, between frames)
    Py_RETURN_NONE;
  }
  // drop what the endpoint took or what was reclaimed; on one channel, a take gives up what
  // it had not taken before it. The list is replaced only once the walk succeeded.
  std::deque<Entry> kept;  // its entries hold references of their own
  long long skipped = 0;
  const auto release_kept = [&kept]() {
      for (Entry & entry : kept) {
        drop(entry);
      }
      kept.clear();
    };
  for (const Entry & entry : inflight) {
    const int is_current = current(entry);
    const int is_settled = is_current > 0 ? settled(entry.slot, ledger->token) : 0;
    if (is_current < 0 || is_settled < 0) {
      release_kept();
      return nullptr;
    }
    if (is_current == 0) {  // reclaimed or removed: nothing left to protect
      continue;
    }
    if (is_settled) {
      if (ledger->per_channel) {  // taken in order: what it had not taken, it dropped
        for (const Entry & older : kept) {
          const int given = give_up(ledger, older);
          if (given < 0) {
            release_kept();
            return nullptr;
          }
          skipped += given;
        }
        release_kept();
      }
      continue;
    }
    kept.push_back(Entry{Py_NewRef(entry.slot), entry.generation, entry.seq});
  }
  clear_inflight(ledger);
  inflight.swap(kept);
  if (add_counter(counters, s_released_skipped, skipped) < 0) {
    return nullptr;
  }
  long long depth = 0;
  bool known = false;
  if (!depth_of(ledger, &depth, &known)) {
    return nullptr;
  }
  if (depth > 0 && !inflight.empty()) {  // seq is the message being described now
    // what was sent counts (N newer), or, with `delivered`, what reached the reader:
    // everything up to seq - 1, so more than N newer must have been sent
    const bool asks = ledger->delivered != Py_None;
    const long long behind = asks ? depth + 1 : depth;
    if (ledger->seq - inflight.front().seq >= behind) {
      int delivered = 1;
      if (asks) {
        PyObject * answer = PyObject_CallNoArgs(ledger->delivered);
        delivered = answer ? PyObject_IsTrue(answer) : -1;
        Py_XDECREF(answer);
        if (delivered < 0) {
          return nullptr;
        }
      }
      long long window = 0;
      while (delivered && !inflight.empty() && ledger->seq - inflight.front().seq >= behind) {
        if (!give_up_oldest(ledger, &window)) {
          return nullptr;
        }
      }
      if (add_counter(counters, s_released_window, window) < 0) {
        return nullptr;
      }
    }
  }
  if (!known) {  // it may no longer hold its oldest: give them up
    long long share = 0;
    while (!inflight.empty()) {
      const int past = past_share(ledger, false, 0);
      if (past < 0) {
        return nullptr;
      }
      if (!past) {
        break;
      }
      if (!give_up_oldest(ledger, &share)) {
        return nullptr;
      }
    }
    if (add_counter(counters, s_released_share, share) < 0) {
      return nullptr;
    }
  }
  Py_RETURN_NONE;
}

PyObject * ledger_full(PyObject * self, PyObject *)
{
  auto * ledger = as_ledger(self);
  if (!ready(ledger)) {
    return nullptr;
  }
  long long depth = 0;
  bool known = false;
  if (!depth_of(ledger, &depth, &known)) {
    return nullptr;
  }
  if (!known || ledger->inflight->empty()) {
    Py_RETURN_FALSE;
  }
  const int past = past_share(ledger, true, depth);
  return past < 0 ? nullptr : PyBool_FromLong(past);
}

PyObject * ledger_entries(PyObject * self, PyObject *)
{
  auto * ledger = as_ledger(self);
  if (!ready(ledger)) {
    return nullptr;
  }
  PyObject * list = PyList_New(0);
  for (const Entry & entry : *ledger->inflight) {
    PyObject * item = list ? Py_BuildValue("(OLL)", entry.slot, entry.generation, entry.seq) :
      nullptr;
    if (item == nullptr || PyList_Append(list, item) < 0) {
      Py_XDECREF(item);
      Py_XDECREF(list);
      return nullptr;
    }
    Py_DECREF(item);
  }
  return list;
}

PyObject * ledger_in_flight(PyObject * self, void *)
{
  auto * ledger = as_ledger(self);
  return ready(ledger) ? PyLong_FromSize_t(ledger->inflight->size()) : nullptr;
}

/// An optional object field's value (None when unset).
PyObject * optional(PyObject * field) {return Py_NewRef(field ? field : Py_None);}

/// Set an optional object field to None or a value `accepts`; -1 with the TypeError `message`
/// otherwise.
int set_optional(PyObject ** field, PyObject * value, bool accepts, const char * message)
{
  if (value == nullptr || (value != Py_None && !accepts)) {
    PyErr_SetString(PyExc_TypeError, message);
    return -1;
  }
  Py_XSETREF(*field, Py_NewRef(value));
  return 0;
}

PyObject * ledger_get_depth(PyObject * self, void *) {return optional(as_ledger(self)->depth);}

int ledger_set_depth(PyObject * self, PyObject * value, void *)
{
  return set_optional(&as_ledger(self)->depth, value, value && PyLong_Check(value),
    "depth must be None or an int");
}

PyObject * ledger_get_delivered(PyObject * self, void *)
{
  return optional(as_ledger(self)->delivered);
}

int ledger_set_delivered(PyObject * self, PyObject * value, void *)
{
  return set_optional(&as_ledger(self)->delivered, value, value && PyCallable_Check(value),
    "delivered must be None or a callable");
}

PyMethodDef ledger_methods[] = {
  RBPY_METHOD("record", ledger_record, METH_O,
    "record(slot)\n--\n\nOne descriptor of the slot's generation is sent with the current "
    "message number."),
  RBPY_METHOD("settle", ledger_settle, METH_O,
    "settle(counters)\n--\n\nBring the in-flight list up to date before message `seq` is "
    "sent (see demo_buffer_backend.ledgers)."),
  RBPY_METHOD("full", ledger_full, METH_NOARGS,
    "full()\n--\n\nThe endpoint, whose history is known, has its share in flight, all of it "
    "still takeable (after settle())."),
  RBPY_METHOD("_entries", ledger_entries, METH_NOARGS,
    "_entries()\n--\n\nThe descriptors in flight, oldest first: (slot, generation, seq)."),
  RBPY_METHODS_END,
};

PyMemberDef ledger_members[] = {
  {"token", T_OBJECT, offsetof(LedgerObject, token), READONLY,
    "The endpoint's process token."},
  {"seq", T_LONGLONG, offsetof(LedgerObject, seq), 0, "Messages described for the endpoint."},
  {"per_channel", T_BOOL, offsetof(LedgerObject, per_channel), READONLY,
    "Whether the ledger sees the messages of one channel only (the in-order rule applies)."},
  {nullptr, 0, 0, 0, nullptr},
};

PyGetSetDef ledger_getset[] = {
  {"depth", ledger_get_depth, ledger_set_depth,
    "KEEP_LAST depth, 0 for KEEP_ALL, None when unknown.", nullptr},
  {"delivered", ledger_get_delivered, ledger_set_delivered,
    "Whether the endpoint's reader received everything sent so far (None: not known).",
    nullptr},
  {"in_flight", ledger_in_flight, nullptr, "Descriptors in flight.", nullptr},
  {nullptr, nullptr, nullptr, nullptr, nullptr},
};

PyType_Slot ledger_slots[] = {
  {Py_tp_doc, const_cast<char *>(
      "LedgerCore(token, depth, per_channel, delivered, limits)\n--\n\n"
      "The rules of a demo endpoint ledger; base of demo_buffer_backend.ledgers."
      "EndpointLedger, which supplies _share(history_known, depth).")},
  {Py_tp_init, reinterpret_cast<void *>(ledger_init)},
  {Py_tp_new, reinterpret_cast<void *>(PyType_GenericNew)},
  {Py_tp_dealloc, reinterpret_cast<void *>(ledger_dealloc)},
  {Py_tp_traverse, reinterpret_cast<void *>(ledger_traverse)},
  {Py_tp_clear, reinterpret_cast<void *>(ledger_clear)},
  {Py_tp_methods, ledger_methods},
  {Py_tp_members, ledger_members},
  {Py_tp_getset, ledger_getset},
  {0, nullptr},
};

PyType_Spec ledger_spec = {
  "rosidl_buffer_py._native.LedgerCore",
  sizeof(LedgerObject),
  0,
  Py_TPFLAGS_DEFAULT | Py_TPFLAGS_BASETYPE | Py_TPFLAGS_HAVE_GC,
  ledger_slots,
};

}  // namespace

int add_demo_ledger_type(PyObject * module)
{
  if (!intern(&s_closed, "closed") || !intern(&s_generation, "generation") ||
    !intern(&s_capacity, "capacity") || !intern(&s_sent, "sent") ||
    !intern(&s_taken, "taken") || !intern(&s_released, "released") ||
    !intern(&s_released_skipped, "released_skipped") ||
    !intern(&s_released_window, "released_window") ||
    !intern(&s_released_share, "released_share") ||
    !intern(&s_max_inflight_per_peer, "max_inflight_per_peer") ||
    !intern(&s_max_slots, "max_slots") || !intern(&s_max_pool_bytes, "max_pool_bytes"))
  {
    return -1;
  }
  return rbpy_glue::add_type(module, &ledger_spec) ? 0 : -1;
}
