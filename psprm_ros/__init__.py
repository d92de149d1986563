"""ROS 2 Jazzy node suite around :mod:`psprm_core`.

Lifecycle nodes: :mod:`.roadmap_server`, :mod:`.perception_scorer`, :mod:`.replan_monitor`, :mod:`.robot_adapter`
(all in one process: :mod:`.all_in_one`); a simulated robot behind the real interfaces: :mod:`.sim_robot`; tools:
:mod:`.mocap_replay`, :mod:`.latency_bench`, :mod:`.demo`, :mod:`.soak`, :mod:`.warm_up`. Importing this package does
no work and does not import rclpy; each module imports ROS only inside the functions that need it.
"""

__all__ = ["adapters", "base_follower", "conversions", "core", "frames", "markers", "robot_state"]
