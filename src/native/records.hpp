// recv_records: what a SOCK_SEQPACKET peer sent, read without raising (see records.cpp).
#ifndef ROSIDL_BUFFER_PY_NATIVE__RECORDS_HPP_
#define ROSIDL_BUFFER_PY_NATIVE__RECORDS_HPP_

#define PY_SSIZE_T_CLEAN
#include <Python.h>

/// Add `recv_records` to `module`. Returns 0 or -1 with an exception set.
int add_records(PyObject * module);

#endif  // ROSIDL_BUFFER_PY_NATIVE__RECORDS_HPP_
