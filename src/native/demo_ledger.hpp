// LedgerCore: the rules of the demo backend's per-endpoint ledgers (see demo_ledger.cpp).
#ifndef ROSIDL_BUFFER_PY_NATIVE__DEMO_LEDGER_HPP_
#define ROSIDL_BUFFER_PY_NATIVE__DEMO_LEDGER_HPP_

#define PY_SSIZE_T_CLEAN
#include <Python.h>

/// Add the LedgerCore type to `module`. Returns 0 or -1 with an exception set.
int add_demo_ledger_type(PyObject * module);

#endif  // ROSIDL_BUFFER_PY_NATIVE__DEMO_LEDGER_HPP_
