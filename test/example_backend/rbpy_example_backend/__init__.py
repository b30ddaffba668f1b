"""rbpy_example_backend: the ``filestore`` buffer backend, a third-party rosidl_buffer_py plugin.

Payloads live in files of a directory that cooperating processes share (the environment variable
``RBPY_EXAMPLE_STORE_DIR``). A descriptor names a link to the file made for one subscriber, the
size and the CRC-32; the subscriber maps the file read-only and unlinks its link. See
docs/backends.md.
"""
from rbpy_example_backend.backend import (BACKEND_TYPE, STORE_DIR_ENV, FileStoreBackend,
                                          FileStoreBuffer)

__all__ = ['BACKEND_TYPE', 'STORE_DIR_ENV', 'FileStoreBackend', 'FileStoreBuffer']
