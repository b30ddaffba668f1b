"""Runnable rclpy nodes (``ros2 run rosidl_buffer_py <name>``) used by demos, tests and benchmarks."""
