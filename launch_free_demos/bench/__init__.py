"""The benchmarks, behind one entry: ``./dev bench [NAME] [args]`` (``python -m
launch_free_demos.bench``, see :mod:`.__main__`). Each NAME is a module here and the full suite
is :mod:`.suite`; :mod:`.measured` measures node processes from outside, :mod:`.stats` holds the
statistics they all use, :mod:`.peers` the peer transports the suite compares with."""
