"""legacy_image_publisher: image_publisher with plain rclpy only (no rosidl_buffer_py wrapper)."""
from rosidl_buffer_py.nodes.image_publisher import legacy_main

if __name__ == '__main__':
    raise SystemExit(legacy_main())
