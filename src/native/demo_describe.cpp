// describe_linked: a demo publisher's descriptor of a frame, for a subscriber process that
// has mapped the frame's segment, in one native call; describe_steady: the same under the
// pool's guard, for a Buffer (a publisher's steady describer, with no Python frame between
// its lane and this code).
//
// demo_buffer_backend.pool.Pool.describe runs for every descriptor a publisher sends, on cold
// caches at camera rates, where each Python line costs ten to thirty times its warm cost. This
// is its steady case, as pool.py describes it: the pin is current; the endpoint is of another
// process, whose link is up, which accepted the slot's segment and has not hung up; and the
// endpoint's ledger has room once settled. It then does what Pool.describe does: counts the
// message (ledger.seq), settles the ledger, records the slot in flight, stamps the slot's last
// use, counts the descriptor and returns the pin's packed descriptor.
//
// Anything else gets None, and Pool.describe's Python path does the same and handles the rest
// (the pattern of open_mapped). Nothing is changed then, except for a ledger found full once
// settled: its message count is put back, and the Python path, which reads the link's answers
// first, counts it again and settles again (at the same count: what one later settle gives).
#include "demo_describe.hpp"

#include <time.h>

#include "py_glue.hpp"

namespace
{

using rbpy_glue::add_counter;
using rbpy_glue::int_attr;
using rbpy_glue::intern;
using rbpy_glue::set_int_attr;

PyObject * s_slot, * s_owner, * s_slots, * s_closed, * s_generation, * s_token, * s_links;
PyObject * s_by_token, * s_id, * s_verdicts, * s_kind, * s_gone, * s_segments, * s_seq;
PyObject * s_counters, * s_settle, * s_full, * s_record, * s_last_used;
PyObject * s_descriptors_created, * s_packed;
PyObject * s_pin, * s_guard, * s_lock, * s_acquire, * s_release, * s_pending, * s_drain;

/// A new reference (or nullptr), released at the end of its scope.
class Ref
{
public:
  explicit Ref(PyObject * obj) : obj_(obj) {}
  ~Ref() {Py_XDECREF(obj_);}
  Ref(const Ref &) = delete;
  Ref & operator=(const Ref &) = delete;
  PyObject * get() const {return obj_;}
  explicit operator bool() const {return obj_ != nullptr;}

private:
  PyObject * obj_;
};

/// `mapping[key]` of a dict (a new reference); nullptr when absent (no exception) or on error
/// (an exception set).
PyObject * item_of(PyObject * mapping, PyObject * key, const char * what)
{
  if (!PyDict_Check(mapping)) {
    PyErr_Format(PyExc_TypeError, "%s must be a dict, got %.100s", what,
      Py_TYPE(mapping)->tp_name);
    return nullptr;
  }
  return Py_XNewRef(PyDict_GetItemWithError(mapping, key));
}

/// Whether the steady case applies to `pin` (whose slot is `slot`) and `ledger`: 1, 0, or -1
/// with an exception set. Reads only.
int steady(long long accepted, PyObject * pool, PyObject * pin, PyObject * ledger,
  PyObject * slot)
{
  // the pin is current: Pool.describe's inlined slot.current(pin.generation)
  Ref owner(PyObject_GetAttr(pin, s_owner)), slots(PyObject_GetAttr(pool, s_slots));
  Ref closed(owner && slots ? PyObject_GetAttr(slot, s_closed) : nullptr);
  if (!closed) {
    return -1;
  }
  const int is_closed = PyObject_IsTrue(closed.get());
  if (owner.get() != slots.get() || is_closed != 0) {
    return is_closed < 0 ? -1 : 0;
  }
  const long long slot_generation = int_attr(slot, s_generation);
  const long long pin_generation = PyErr_Occurred() ? -1 : int_attr(pin, s_generation);
  if (PyErr_Occurred()) {
    return -1;
  }
  if (slot_generation != pin_generation) {
    return 0;
  }
  // an endpoint of another process (this one's adopts its own slot: the Python path)
  Ref token(PyObject_GetAttr(ledger, s_token)), own(PyObject_GetAttr(pool, s_token));
  if (!token || !own) {
    return -1;
  }
  const int is_own = PyObject_RichCompareBool(token.get(), own.get(), Py_EQ);
  if (is_own != 0) {
    return is_own < 0 ? -1 : 0;
  }
  // its link is up and it accepted the segment (else the Python path reads the link first)
  Ref links(PyObject_GetAttr(pool, s_links));
  Ref by_token(links ? PyObject_GetAttr(links.get(), s_by_token) : nullptr);
  Ref link(by_token ? item_of(by_token.get(), token.get(), "links.by_token") : nullptr);
  if (!link) {
    return PyErr_Occurred() ? -1 : 0;
  }
  Ref id(PyObject_GetAttr(slot, s_id)), verdicts(PyObject_GetAttr(link.get(), s_verdicts));
  Ref verdict(id && verdicts ? item_of(verdicts.get(), id.get(), "link.verdicts") : nullptr);
  if (!verdict) {
    return PyErr_Occurred() ? -1 : 0;
  }
  const long long kind = int_attr(verdict.get(), s_kind);
  if (kind == -1 && PyErr_Occurred()) {
    return -1;
  }
  if (kind != accepted) {  // (an int on the wire, a ReplyKind when compared in Python)
    return 0;
  }
  // its process has not hung up (the Python path raises EndpointGone), and the segment was
  // handed over to it
  Ref gone(PyObject_GetAttr(links.get(), s_gone));
  const int is_gone = gone ? PySequence_Contains(gone.get(), token.get()) : -1;
  if (is_gone != 0) {
    return is_gone < 0 ? -1 : 0;
  }
  Ref segments(PyObject_GetAttr(link.get(), s_segments));
  return segments ? PySequence_Contains(segments.get(), id.get()) : -1;
}

/// The steady case's descriptor of `pin` for `ledger` (a new reference), None where the Python
/// path is to run, or nullptr with an exception set. The caller holds the pool's guard.
PyObject * described(long long accepted, PyObject * pool, PyObject * pin, PyObject * ledger)
{
  Ref slot(PyObject_GetAttr(pin, s_slot));
  const int applies = slot ? steady(accepted, pool, pin, ledger, slot.get()) : -1;
  if (applies <= 0) {
    return applies < 0 ? nullptr : Py_NewRef(Py_None);
  }
  const long long seq = int_attr(ledger, s_seq);
  if ((seq == -1 && PyErr_Occurred()) || set_int_attr(ledger, s_seq, seq + 1) < 0) {
    return nullptr;
  }
  Ref counters(PyObject_GetAttr(pool, s_counters));
  Ref settled(counters ? PyObject_CallMethodOneArg(ledger, s_settle, counters.get()) : nullptr);
  Ref full(settled ? PyObject_CallMethodNoArgs(ledger, s_full) : nullptr);
  const int is_full = full ? PyObject_IsTrue(full.get()) : -1;
  if (is_full != 0) {
    if (is_full < 0 || set_int_attr(ledger, s_seq, seq) < 0) {
      return nullptr;
    }
    Py_RETURN_NONE;
  }
  Ref recorded(PyObject_CallMethodOneArg(ledger, s_record, slot.get()));
  if (!recorded) {
    return nullptr;
  }
  timespec now;  // time.monotonic_ns()'s clock
  clock_gettime(CLOCK_MONOTONIC, &now);
  if (set_int_attr(slot.get(), s_last_used, now.tv_sec * 1000000000LL + now.tv_nsec) < 0 ||
    add_counter(counters.get(), s_descriptors_created, 1) < 0)
  {
    return nullptr;
  }
  return PyObject_GetAttr(pin, s_packed);
}

/// `accepted` from the first of `nargs` arguments, which must be `expected`; -1 with an
/// exception set on error.
long long accepted_of(
  const char * name, PyObject * const * args, Py_ssize_t nargs, Py_ssize_t expected)
{
  if (nargs != expected) {
    PyErr_Format(PyExc_TypeError, "%s takes %zd arguments, got %zd", name, expected, nargs);
    return -1;
  }
  return PyLong_AsLongLong(args[0]);
}

// describe_linked(accepted, pool, pin, ledger)
PyObject * describe_linked(PyObject *, PyObject * const * args, Py_ssize_t nargs)
{
  const long long accepted = accepted_of("describe_linked", args, nargs, 4);
  if (accepted == -1 && PyErr_Occurred()) {
    return nullptr;
  }
  return described(accepted, args[1], args[2], args[3]);
}

/// Let go of the guard as `Guard.__exit__` does (its lock released, then the releases queued
/// meanwhile run): `result` when that succeeds, else nullptr with its exception set (`result`
/// dropped). An exception already set stays set, as the one `result` == nullptr carries.
PyObject * let_go(PyObject * guard, PyObject * lock, PyObject * result)
{
  PyObject * type, * value, * traceback;
  PyErr_Fetch(&type, &value, &traceback);
  Ref released(PyObject_CallMethodNoArgs(lock, s_release));
  Ref pending(released ? PyObject_GetAttr(guard, s_pending) : nullptr);
  const int queued = pending ? PyObject_IsTrue(pending.get()) : -1;
  Ref drained(queued > 0 ? PyObject_CallMethodNoArgs(guard, s_drain) : nullptr);
  if (queued < 0 || (queued > 0 && !drained)) {  // (what `with` raises: the exit's error)
    Py_XDECREF(type);
    Py_XDECREF(value);
    Py_XDECREF(traceback);
    Py_XDECREF(result);
    return nullptr;
  }
  PyErr_Restore(type, value, traceback);
  return result;
}

// describe_steady(accepted, pool, ledger, buffer)
PyObject * describe_steady(PyObject *, PyObject * const * args, Py_ssize_t nargs)
{
  const long long accepted = accepted_of("describe_steady", args, nargs, 4);
  if (accepted == -1 && PyErr_Occurred()) {
    return nullptr;
  }
  PyObject * pool = args[1], * ledger = args[2], * buffer = args[3];
  Ref pin(PyObject_GetAttr(buffer, s_pin));  // (a Buffer of another kind has none)
  if (!pin) {
    if (!PyErr_ExceptionMatches(PyExc_AttributeError)) {
      return nullptr;
    }
    PyErr_Clear();
    Py_RETURN_NONE;
  }
  Ref closed(PyObject_GetAttr(pool, s_closed));
  const int is_closed = closed ? PyObject_IsTrue(closed.get()) : -1;
  if (is_closed != 0 || pin.get() == Py_None) {
    return is_closed < 0 ? nullptr : Py_NewRef(Py_None);
  }
  Ref guard(PyObject_GetAttr(pool, s_guard));
  Ref lock(guard ? PyObject_GetAttr(guard.get(), s_lock) : nullptr);
  Ref acquired(lock ? PyObject_CallMethodNoArgs(lock.get(), s_acquire) : nullptr);
  if (!acquired) {
    return nullptr;
  }
  return let_go(guard.get(), lock.get(), described(accepted, pool, pin.get(), ledger));
}

PyMethodDef describe_functions[] = {
  {"describe_linked", reinterpret_cast<PyCFunction>(reinterpret_cast<void (*)(void)>(
      describe_linked)), METH_FASTCALL,
    "describe_linked(accepted, pool, pin, ledger) -> bytes | None\n--\n\n"
    "Pool.describe's steady case (see src/native/demo_describe.cpp), `accepted` the reply "
    "kind of a mapped segment: the pin's packed "
    "descriptor, recorded in the ledger; None, with nothing changed, where the Python path "
    "is to run."},
  {"describe_steady", reinterpret_cast<PyCFunction>(reinterpret_cast<void (*)(void)>(
      describe_steady)), METH_FASTCALL,
    "describe_steady(accepted, pool, ledger, buffer) -> bytes | None\n--\n\n"
    "A publisher's steady describer (Pool.steady_describer): describe_linked for the "
    "Buffer's pin under the pool's guard, taken and let go as `with pool.guard:` does; None "
    "for a Buffer without a pin and for a closed pool."},
  RBPY_METHODS_END,
};

}  // namespace

int add_demo_describe(PyObject * module)
{
  const std::pair<PyObject **, const char *> names[] = {
    {&s_slot, "slot"}, {&s_owner, "owner"}, {&s_slots, "slots"}, {&s_closed, "closed"},
    {&s_generation, "generation"}, {&s_token, "token"}, {&s_links, "links"},
    {&s_by_token, "by_token"}, {&s_id, "id"}, {&s_verdicts, "verdicts"}, {&s_kind, "kind"},
    {&s_gone, "gone"}, {&s_segments, "segments"}, {&s_seq, "seq"}, {&s_counters, "counters"},
    {&s_settle, "settle"}, {&s_full, "full"}, {&s_record, "record"},
    {&s_last_used, "last_used"}, {&s_descriptors_created, "descriptors_created"},
    {&s_packed, "packed"}, {&s_pin, "pin"}, {&s_guard, "guard"}, {&s_lock, "lock"},
    {&s_acquire, "acquire"}, {&s_release, "release"}, {&s_pending, "pending"},
    {&s_drain, "drain"},
  };
  for (const auto & name : names) {
    if (!intern(name.first, name.second)) {
      return -1;
    }
  }
  return PyModule_AddFunctions(module, describe_functions);
}
