// dlpack_capsule: raw memory exported as a DLPack capsule (see dlpack_export.cpp).
#ifndef ROSIDL_BUFFER_PY_NATIVE__DLPACK_EXPORT_HPP_
#define ROSIDL_BUFFER_PY_NATIVE__DLPACK_EXPORT_HPP_

#define PY_SSIZE_T_CLEAN
#include <Python.h>

/// Add `dlpack_capsule` to `module`. Returns 0 or -1 with an exception set.
int add_dlpack_export(PyObject * module);

#endif  // ROSIDL_BUFFER_PY_NATIVE__DLPACK_EXPORT_HPP_
