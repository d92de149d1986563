"""Process entry points shared by the executables: argument handling, rclpy start-up, a multi-threaded executor and a
clean shutdown on SIGINT/SIGTERM.

Usage of every executable::

    <node> [--self-check] [--ros-args --params-file config/ros/dynamic_person.yaml -p name:=value ...]

``--self-check`` imports the node modules and the message packages, prints one JSON line and exits 0 without
starting ROS (used by the colcon build test and the Dockerfile).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from typing import Callable, Sequence

from psprm_core.errors import PsprmError

from .core import autostart
from .heap import freeze_long_lived
from .robots.adapters import import_follow_joint_trajectory
from .spinning import NodeSpinner


def self_check() -> dict:
    """Import everything an installed node needs; returns what was found."""
    import importlib

    import psprm_core
    import psprm_ros

    mods = ["rclpy", "rclpy.lifecycle", "rclpy.action", "std_msgs.msg", "geometry_msgs.msg", "sensor_msgs.msg",
            "nav_msgs.msg", "trajectory_msgs.msg", "visualization_msgs.msg", "diagnostic_msgs.msg", "lifecycle_msgs.msg",
            "rosgraph_msgs.msg", "std_srvs.srv", "psprm_ros.roadmap_server", "psprm_ros.perception_scorer",
            "psprm_ros.replan_monitor", "psprm_ros.robot_adapter", "psprm_ros.sim_robot", "psprm_ros.all_in_one",
            "psprm_ros.mocap_replay", "psprm_ros.harness.soak"]
    for m in mods:
        importlib.import_module(m)

    return {"ok": True, "psprm_ros": psprm_ros.__file__, "psprm_core": psprm_core.__file__, "modules": len(mods),
            "control_msgs": import_follow_joint_trajectory() is not None}


def _raise_on_signals() -> None:
    """SIGINT/SIGTERM end the spin once (KeyboardInterrupt); a repeated signal (a script's trap after the process
    group's) is ignored, so that it cannot interrupt the nodes' shutdown (the adapter's stop) with a traceback."""
    import signal

    def handler(signum, frame):
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        raise KeyboardInterrupt

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)


def start_lifecycles(owners) -> list:
    """Configure and activate every lifecycle node whose ``autostart`` parameter is true, each on its own thread
    (the roadmap server's configure builds or loads the roadmap). Returns the threads."""
    import threading

    threads = []
    for n in owners:
        if not hasattr(n.node, "trigger_configure"):
            continue
        p = getattr(n, "p", {})
        if not p.get("autostart", True):
            continue
        t = threading.Thread(target=autostart, args=(n,), name=f"autostart-{n.node.get_name()}", daemon=True)
        t.start()
        threads.append(t)
    return threads


def _freeze_after(threads) -> None:
    """Once the nodes' start-up ``threads`` are done (modules, models and roadmap loaded), freeze what is alive out of
    the collector's full passes (:func:`~psprm_ros.heap.freeze_long_lived`), on a thread of its own."""
    import threading

    def run():
        for t in threads:
            t.join()

        r = freeze_long_lived()
        logging.getLogger("psprm_ros.runner").info(
            "start-up done: %d objects kept out of full collections (one collection first: %.0f ms)",
            r["frozen"], r["collect_ms"])

    threading.Thread(target=run, name="freeze-after-start", daemon=True).start()


#: Python's GIL switch interval in the node processes (default 0.005 s), see :func:`run_nodes`.
GIL_SWITCH_INTERVAL_S = 0.0005


def run_nodes(factories: Sequence[Callable], args=None, description: str = "", prog: str = "") -> int:
    """Start the nodes made by ``factories`` in one process, each on its own single-threaded executor
    (:class:`~psprm_ros.spinning.NodeSpinner`), and spin until shut down."""
    argv = list(sys.argv if args is None else args)
    from rclpy.utilities import remove_ros_args

    user = remove_ros_args(argv)[1:]
    parser = argparse.ArgumentParser(prog=prog or None, description=(description or "").split("\n\n")[0],
                                     epilog="ROS arguments follow --ros-args, e.g. "
                                            "--ros-args --params-file config/ros/dynamic_person.yaml")
    parser.add_argument("--self-check", action="store_true",
                        help="import the nodes and message packages, print JSON and exit (no ROS start-up)")
    opts = parser.parse_args(user)
    if opts.self_check:
        print(json.dumps(self_check()))
        return 0

    import rclpy
    from rclpy.executors import ExternalShutdownException

    logging.basicConfig(level=logging.INFO, format="[%(levelname)s] [%(name)s]: %(message)s", stream=sys.stderr)
    # The planner thread makes thousands of short torch calls per plan, each releasing and re-taking the GIL; while
    # the executor thread is busy with message callbacks (120 Hz mocap), every re-take can wait a full switch interval
    # (5 ms by default), which stretched a 0.5 s plan to 10-60 s in the demo. A shorter interval bounds that wait.
    sys.setswitchinterval(GIL_SWITCH_INTERVAL_S)
    # rclpy's own SIGINT handler shuts the context down at once, after which no node can publish: the adapter's stop
    # on shutdown would be lost. Here SIGINT/SIGTERM end the spin instead; the nodes are destroyed (an adapter stops
    # the robot) while the context is still up, then it is shut down.
    from rclpy.signals import SignalHandlerOptions

    rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    _raise_on_signals()
    nodes = []
    executor = NodeSpinner()
    try:
        for f in factories:
            n = f()
            nodes.append(n)
            executor.add(n.node)
        executor.start()
        _freeze_after(start_lifecycles(nodes))
        executor.wait()
        for name, exc in executor.errors:
            raise exc
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception as exc:  # configuration errors (unknown scene, bad params file): one line, status 2
        if not rclpy.ok():  # SIGTERM/SIGINT shut the context down while the executor was building its wait set
            return 0
        if not isinstance(exc, (PsprmError, KeyError)):
            raise
        print(f"{parser.prog}: error: {exc}", file=sys.stderr)
        return 2
    finally:
        # executors first (no callback may run on a node being destroyed), then the nodes (an adapter publishes its
        # stop: the context is still up), then the context
        executor.shutdown(timeout_sec=1.0)
        for n in reversed(nodes):
            try:
                n.destroy()
            except Exception:
                pass
        rclpy.try_shutdown()
    return 0
