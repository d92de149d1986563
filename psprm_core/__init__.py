"""psprm_core: perception-score-guided probabilistic roadmaps (PS-PRM) for high-DoF robots with a camera.

Pure-Python planning library; it never imports ROS. Heavy objects (robot models, networks, simulators) are built by
explicit calls, never at import time.
"""

__version__ = "0.1.0"
