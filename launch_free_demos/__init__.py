"""Runnable multi-process demos of rosidl_buffer_py (no ros2 launch needed): the image demo
(:mod:`.image_demo`), the benchmarks (:mod:`.bench`), and the process runner they and the tests
start nodes with (:mod:`.runner`, :mod:`.domains`).

Not installed (setup.py ships the library, its nodes and tools, and the backends): ``./dev demo``
and ``./dev bench`` run it from the checkout's root, and the tests find it there
(test/conftest.py, the path fix of the harness scripts)."""
