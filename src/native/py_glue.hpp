// The Python C-API glue every file of rosidl_buffer_py._native shares: method-table entries,
// type and function registration, GIL-released calls, and errors found without the GIL that
// are raised once it is back. Nothing here knows about ROS or DDS.
#ifndef ROSIDL_BUFFER_PY_NATIVE__PY_GLUE_HPP_
#define ROSIDL_BUFFER_PY_NATIVE__PY_GLUE_HPP_

#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <cstring>
#include <string>
#include <utility>

/// A PyMethodDef entry for the C function `fn` (METH_VARARGS/O/NOARGS, or with
/// METH_KEYWORDS), named `name`.
#define RBPY_METHOD(name, fn, flags, doc) {name, rbpy_glue::as_method(fn), flags, doc}
/// A module function named as its C function.
#define RBPY_FUNCTION(fn, flags, doc) RBPY_METHOD(#fn, fn, flags, doc)
#define RBPY_METHODS_END {nullptr, nullptr, 0, nullptr}

namespace rbpy_glue
{

inline PyCFunction as_method(PyCFunction fn) {return fn;}
inline PyCFunction as_method(PyCFunctionWithKeywords fn)
{
  return reinterpret_cast<PyCFunction>(reinterpret_cast<void (*)(void)>(fn));
}

/// Releases the GIL for its scope. Never touch Python objects inside.
class GilRelease
{
public:
  GilRelease() : state_(PyEval_SaveThread()) {}
  ~GilRelease() {PyEval_RestoreThread(state_);}
  GilRelease(const GilRelease &) = delete;
  GilRelease & operator=(const GilRelease &) = delete;

private:
  PyThreadState * state_;
};

/// `f()` with the GIL released; returns what it returns.
template<typename F>
auto without_gil(F && f) -> decltype(f())
{
  GilRelease nogil;
  return f();
}

/// An error found while the GIL was released, raised once it is back (GIL held for raise()).
class PendingError
{
public:
  void set(PyObject * type, std::string message)
  {
    type_ = type;
    message_ = std::move(message);
  }
  explicit operator bool() const {return type_ != nullptr;}
  /// Set the Python exception; returns nullptr (for PyObject * functions).
  PyObject * raise() const
  {
    PyErr_SetString(type_, message_.c_str());
    return nullptr;
  }

private:
  PyObject * type_ = nullptr;
  std::string message_;
};

/// Keeps the current exception aside for its scope (a tp_dealloc that may raise and report).
class SavedException
{
public:
  SavedException() {PyErr_Fetch(&type_, &value_, &traceback_);}
  ~SavedException() {PyErr_Restore(type_, value_, traceback_);}
  SavedException(const SavedException &) = delete;
  SavedException & operator=(const SavedException &) = delete;

private:
  PyObject * type_;
  PyObject * value_;
  PyObject * traceback_;
};

/// PyModule_AddObjectRef that takes over `value`'s reference (nullptr: an exception is set).
inline int add_object(PyObject * module, const char * name, PyObject * value)
{
  const int result = value ? PyModule_AddObjectRef(module, name, value) : -1;
  Py_XDECREF(value);
  return result;
}

/// Create the type of `spec` and add it to `module` under its short name. Returns the type
/// (a borrowed reference: the module holds it) or nullptr with an exception set.
inline PyObject * add_type(PyObject * module, PyType_Spec * spec)
{
  PyObject * type = PyType_FromSpec(spec);
  const char * dot = std::strrchr(spec->name, '.');
  return add_object(module, dot ? dot + 1 : spec->name, Py_XNewRef(type)) < 0 ? nullptr : type;
}

/// Intern `text` into `*name` (an attribute name read on a hot path). False with an exception
/// set on error.
inline bool intern(PyObject ** name, const char * text)
{
  *name = PyUnicode_InternFromString(text);
  return *name != nullptr;
}

/// `obj.name` as a long long; -1 with an exception set on error (check PyErr_Occurred()).
inline long long int_attr(PyObject * obj, PyObject * name)
{
  PyObject * value = PyObject_GetAttr(obj, name);
  if (value == nullptr) {
    return -1;
  }
  const long long result = PyLong_AsLongLong(value);
  Py_DECREF(value);
  return result;
}

/// `obj.name = value`, consuming `value` (a new reference; nullptr: the exception its
/// maker set is passed on). 0, or -1 with an exception set.
inline int set_attr(PyObject * obj, PyObject * name, PyObject * value)
{
  const int result = value ? PyObject_SetAttr(obj, name, value) : -1;
  Py_XDECREF(value);
  return result;
}

/// `obj.name = value` for an int. 0, or -1 with an exception set.
inline int set_int_attr(PyObject * obj, PyObject * name, long long value)
{
  return set_attr(obj, name, PyLong_FromLongLong(value));
}

/// `obj.name += delta` (an int attribute, a counter). 0, or -1 with an exception set.
inline int add_counter(PyObject * obj, PyObject * name, long long delta)
{
  if (delta == 0) {
    return 0;
  }
  const long long now = int_attr(obj, name);
  if (now == -1 && PyErr_Occurred()) {
    return -1;
  }
  return set_int_attr(obj, name, now + delta);
}

}  // namespace rbpy_glue

#endif  // ROSIDL_BUFFER_PY_NATIVE__PY_GLUE_HPP_
