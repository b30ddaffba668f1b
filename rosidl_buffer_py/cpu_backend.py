"""The built-in ``cpu`` backend: ordinary bytes, serialized exactly as legacy ``uint8[]``."""
from typing import Optional

from rosidl_buffer_py.backend import BufferBackend, EndpointInfo
from rosidl_buffer_py.buffer import Buffer

CPU_BACKEND = 'cpu'


class CpuBackend(BufferBackend):
    """CPU memory. It has no descriptors: CPU data always travels as serialized bytes."""

    def get_backend_type(self) -> str:
        return CPU_BACKEND

    def create_descriptor_with_endpoint(self, buffer: Buffer,
                                        endpoint_info: EndpointInfo) -> Optional[bytes]:
        return None

    def from_descriptor_with_endpoint(self, descriptor: bytes,
                                      endpoint_info: EndpointInfo) -> Buffer:
        raise ValueError('the cpu backend has no descriptors: CPU data is sent as bytes')
