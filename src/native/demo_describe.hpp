// describe_linked, describe_steady: the demo publisher's steady descriptor, in one call (see
// demo_describe.cpp).
#ifndef ROSIDL_BUFFER_PY_NATIVE__DEMO_DESCRIBE_HPP_
#define ROSIDL_BUFFER_PY_NATIVE__DEMO_DESCRIBE_HPP_

#define PY_SSIZE_T_CLEAN
#include <Python.h>

/// Add describe_linked and describe_steady to `module`. Returns 0 or -1 with an exception set.
int add_demo_describe(PyObject * module);

#endif  // ROSIDL_BUFFER_PY_NATIVE__DEMO_DESCRIBE_HPP_
