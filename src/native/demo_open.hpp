// open_mapped: a demo descriptor taken, its segment's view opened (see demo_open.cpp).
#ifndef ROSIDL_BUFFER_PY_NATIVE__DEMO_OPEN_HPP_
#define ROSIDL_BUFFER_PY_NATIVE__DEMO_OPEN_HPP_

#define PY_SSIZE_T_CLEAN
#include <Python.h>

/// Add `open_mapped` to `module`. Returns 0 or -1 with an exception set.
int add_demo_open(PyObject * module);

#endif  // ROSIDL_BUFFER_PY_NATIVE__DEMO_OPEN_HPP_
