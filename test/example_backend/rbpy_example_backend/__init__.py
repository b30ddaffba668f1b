"""rbpy_example_backend: the ``filestore`` buffer backend, a third-party rosidl_buffer_py plugin.

Payloads live in files of a directory that cooperating processes share (the environment variable
``RBPY_EXAMPLE_STORE_DIR``). A descriptor names the file, its size and its CRC-32; a subscriber
maps the file read-only. See README.md.
"""
from rbpy_example_backend.backend import (BACKEND_TYPE, RETAIN_ENV, STORE_DIR_ENV,
                                          FileStoreBackend, FileStoreBuffer)

__all__ = ['BACKEND_TYPE', 'RETAIN_ENV', 'STORE_DIR_ENV', 'FileStoreBackend', 'FileStoreBuffer']
