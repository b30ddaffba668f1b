"""Runnable multi-process demos of rosidl_buffer_py (no ros2 launch needed): the image demo
(:mod:`.image_demo`), the benchmarks (:mod:`.bench`), and the process runner they and the tests
start nodes with (:mod:`.runner`, :mod:`.domains`)."""
