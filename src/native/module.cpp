// rosidl_buffer_py._native: the package's only native extension.
//
// Narrow API, documented in src/native/README.md:
//   BufferBase  - buffer-protocol base class of rosidl_buffer_py.Buffer (Python 3.11 has no
//                 __buffer__ for Python classes).
//   rmw_fastrtps layer (dds_*.cpp) - endpoint GIDs, USER_DATA, discovery tap, channels below rcl,
//                 take with publisher GID.
//   dlpack_capsule - raw host or device memory as a DLPack capsule that keeps its owner alive.
//   recv_records - a SOCK_SEQPACKET socket's queued records, read without raising.
//   LedgerCore - the demo backend's ledger rules, run on every descriptor described (#30).
//   open_mapped - a demo descriptor's view opened, for every descriptor taken (#30).
//   describe_linked, describe_steady - a demo descriptor described, for every descriptor sent
//                 (#30).
#include "buffer_base.hpp"
#include "dds_common.hpp"
#include "demo_describe.hpp"
#include "demo_ledger.hpp"
#include "demo_open.hpp"
#include "dlpack_export.hpp"
#include "records.hpp"

namespace
{

PyModuleDef native_module = {
  PyModuleDef_HEAD_INIT,
  "rosidl_buffer_py._native",
  "Native helpers of rosidl_buffer_py: only what Python cannot do.",
  -1,
  nullptr, nullptr, nullptr, nullptr, nullptr,
};

}  // namespace

PyMODINIT_FUNC PyInit__native(void)
{
  PyObject * module = PyModule_Create(&native_module);
  if (module == nullptr) {
    return nullptr;
  }
  if (add_buffer_base_type(module) < 0 || add_dds_api(module) < 0 ||
    add_dlpack_export(module) < 0 || add_records(module) < 0 ||
    add_demo_ledger_type(module) < 0 || add_demo_open(module) < 0 ||
    add_demo_describe(module) < 0)
  {
    Py_DECREF(module);
    return nullptr;
  }
  return module;
}
