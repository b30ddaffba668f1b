// Declarations shared by the modules of rosidl_buffer_py._native.
#ifndef ROSIDL_BUFFER_PY_NATIVE__BUFFER_BASE_HPP_
#define ROSIDL_BUFFER_PY_NATIVE__BUFFER_BASE_HPP_

#define PY_SSIZE_T_CLEAN
#include <Python.h>

/// Add the BufferBase type (buffer-protocol re-exporter) to `module`. Returns 0 or -1 with an
/// exception set.
int add_buffer_base_type(PyObject * module);

#endif  // ROSIDL_BUFFER_PY_NATIVE__BUFFER_BASE_HPP_
