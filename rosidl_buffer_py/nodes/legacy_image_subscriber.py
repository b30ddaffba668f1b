"""legacy_image_subscriber: image_subscriber with plain rclpy only (no rosidl_buffer_py wrapper)."""
from rosidl_buffer_py.nodes.image_subscriber import legacy_main

if __name__ == '__main__':
    raise SystemExit(legacy_main())
