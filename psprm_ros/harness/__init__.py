"""Clients that drive the node suite rather than nodes of it: the closed-loop demo (the main job), the soak, the
latency benchmark, and the probe that tests and these tools use to publish poses and goals and to record what the
suite does. Each runs as ``python -m psprm_ros.harness.<name>`` (``ros2 run psprm_ros <name>`` once installed)."""
