"""Runnable multi-process demos and benchmarks of rosidl_buffer_py (no ros2 launch needed)."""
