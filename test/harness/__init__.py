"""The test harness (not shipped): what the tests start and share, and the suites a developer
runs by hand.

- :mod:`.scenarios`: upstream's launch tests as named multi-process scenarios
  (``.venv/bin/python test/harness/scenarios.py [NAME ...]``);
- :mod:`.equivalence`, :mod:`.probe_node`: the same graphs with stock and with our endpoints,
  compared (``.venv/bin/python test/harness/equivalence.py [names] [--echo]``);
- :mod:`.installed`: where the package under test is installed; :mod:`.in_process`: helpers
  for tests in one process;
- :mod:`.demo_backend_peer`, :mod:`.native_dds_peer`: the other process of a two-process test;
- :mod:`.measure_inspector`: how often ``buffer_topic_info`` sees the whole graph.

Processes are started through :mod:`launch_free_demos.runner`, which the demos use too.
"""
