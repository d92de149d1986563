"""ROS 2 Jazzy node suite around :mod:`psprm_core`.

Nodes: :mod:`.roadmap_server`, :mod:`.perception_scorer`, :mod:`.replan_monitor`, :mod:`.all_in_one`; tools:
:mod:`.mocap_replay`, :mod:`.latency_bench`, :mod:`.demo`. Importing this package does no work and does not import
rclpy; each module imports ROS only inside the functions that need it.
"""

__all__ = ["conversions", "core", "markers"]
