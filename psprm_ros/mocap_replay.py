"""``mocap_replay``: publish recorded rigid-body poses as ``geometry_msgs/PoseStamped`` topics at their recorded rate.

    mocap_replay config/recordings/person_turning.csv [--prefix /mocap] [--rate 1.0] [--loop] [--bodies a,b]
                 [--keep-stamps] [--clock] [--frame world] [--ros-args ...]

Input: a CSV recording or a rosbag2 (read with ``rosbags``; format in :mod:`psprm_ros.interfaces.recordings`). Each body
is published on ``<prefix>/<body>/pose`` with sensor-data QoS (best effort, keep last 1), like a motion-capture driver.
Stamps are re-written to the current time; ``--keep-stamps`` keeps the recorded ones. ``--clock`` publishes
``/clock`` (rosgraph_msgs/Clock) with the replay's time -- the recorded time with ``--keep-stamps``, else the wall
time at the start plus the replayed time -- so nodes started with ``use_sim_time:=true`` see the poses as fresh
(without it, recorded stamps are stale against the wall clock and every pose is refused). ``--frame`` overrides the
recorded frame id (e.g. ``world``, as vrpn_mocap publishes). Pacing runs on its own thread against a monotonic
clock, so the rate holds at 120 Hz without drift.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from typing import Callable, Optional

import numpy as np

from psprm_core.errors import InputError

from .heap import freeze_long_lived
from .interfaces import conversions as cv
from .interfaces.recordings import Recording, load_recording
from .runner import self_check


class Replayer:
    """Publishes a :class:`Recording` through ``node`` (one publisher per body: ``<prefix>/<body>/pose``, or the
    topic ``topics`` names for it, e.g. the replan monitor's ``target_topics`` / ``obstacle_topics``)."""

    def __init__(self, node, rec: Recording, prefix: str = "/mocap", rate: float = 1.0, loop: bool = False,
                 bodies: Optional[list] = None, keep_stamps: bool = False,
                 on_sample: Optional[Callable] = None, clock: bool = False, frame: str = "",
                 topics: Optional[dict] = None):
        from geometry_msgs.msg import PoseStamped
        from rclpy.qos import qos_profile_sensor_data

        self.node, self.rec, self.rate, self.loop = node, rec, float(rate), loop
        self.keep_stamps = keep_stamps
        self.on_sample = on_sample
        self.frame = frame
        self.pub_clock = None
        if clock:
            from rosgraph_msgs.msg import Clock

            self.pub_clock = node.create_publisher(Clock, "/clock", 10)
        self._time0 = 0.0  # replay time of recording time 0 (set at each pass)
        want = bodies or rec.bodies
        unknown = set(want) - set(rec.bodies)
        if unknown:
            raise InputError(f"bodies not in the recording: {', '.join(sorted(unknown))} (have {rec.bodies})")
        self.selected = np.isin(rec.body, [rec.bodies.index(b) for b in want])
        topics = topics or {}
        self.topics = {b: topics.get(b) or f"{prefix}/{b}/pose" for b in rec.bodies if b in want}
        self.pubs = {i: node.create_publisher(PoseStamped, self.topics[b], qos_profile_sensor_data)
                     for i, b in enumerate(rec.bodies) if b in want}
        self.published = 0
        self._stop = threading.Event()
        self._thread: Optional[threading.Thread] = None

    def start(self) -> "Replayer":
        self._thread = threading.Thread(target=self.run, name="mocap-replay", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)

    def join(self, timeout: Optional[float] = None) -> None:
        if self._thread is not None:
            self._thread.join(timeout)

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def run(self) -> None:
        rec = self.rec
        idx = np.nonzero(self.selected)[0]
        pass_no = 0
        while not self._stop.is_set():
            t0 = time.monotonic()
            # recording time 0 on the replay's clock: the recorded stamp of the first sample (--keep-stamps) or the
            # wall time now; a looped pass continues after the previous one, so time never runs backwards
            period = rec.duration / max(1, len(rec.times) - 1)
            if pass_no == 0:
                self._time0 = rec.t0 if self.keep_stamps else time.time()
            else:
                self._time0 += rec.duration + period
            pass_no += 1
            for i in idx:
                due = t0 + rec.times[i] / self.rate
                delay = due - time.monotonic()
                if delay > 0 and self._stop.wait(delay):
                    return
                self.publish(i)
            if not self.loop:
                return

    def publish(self, i: int) -> None:
        rec = self.rec
        b = int(rec.body[i])
        if self.keep_stamps or self.pub_clock is not None:
            stamp = cv.sec_to_stamp(self._time0 + rec.times[i])  # the recorded stamp (or replay time with --clock)
        else:
            stamp = self.node.get_clock().now().to_msg()
        if self.pub_clock is not None:
            from rosgraph_msgs.msg import Clock

            self.pub_clock.publish(Clock(clock=stamp))
        msg = cv.pose_stamped(rec.P[i], rec.Q[i], self.frame or rec.frames[b], stamp)
        self.pubs[b].publish(msg)
        self.published += 1
        if self.on_sample is not None:
            self.on_sample(rec.bodies[b], rec.times[i], rec.P[i], rec.Q[i])


def main(args=None) -> int:
    argv = list(sys.argv if args is None else args)
    from rclpy.utilities import remove_ros_args

    ap = argparse.ArgumentParser(prog="mocap_replay", description=__doc__.split("\n\n")[0])
    ap.add_argument("recording", nargs="?", default="", help="CSV file or rosbag2 directory/file")
    ap.add_argument("--prefix", default="/mocap", help="topic prefix: <prefix>/<body>/pose (default /mocap)")
    ap.add_argument("--rate", type=float, default=1.0, help="playback speed factor (default 1.0 = recorded rate)")
    ap.add_argument("--loop", action="store_true", help="repeat until stopped")
    ap.add_argument("--bodies", default="", help="comma-separated bodies to publish (default all)")
    ap.add_argument("--keep-stamps", action="store_true", help="keep the recorded stamps instead of now")
    ap.add_argument("--clock", action="store_true", help="publish /clock with the replay's time (use_sim_time nodes)")
    ap.add_argument("--frame", default="", help="frame id of every pose (default: the recorded frames)")
    ap.add_argument("--wait-subscribers", type=float, default=5.0,
                    help="wait up to this many seconds for a subscriber before starting (default 5)")
    ap.add_argument("--self-check", action="store_true", help="import and exit (see runner --self-check)")
    a = ap.parse_args(remove_ros_args(argv)[1:])
    if a.self_check:
        import json

        print(json.dumps(self_check()))
        return 0
    if not a.recording:
        ap.error("a recording is required")
    try:
        rec = load_recording(a.recording)
    except (OSError, ValueError) as exc:
        print(f"mocap_replay: error: {exc}", file=sys.stderr)
        return 2
    import rclpy
    from rclpy.executors import ExternalShutdownException

    rclpy.init(args=argv)
    node = rclpy.create_node("mocap_replay")
    log = node.get_logger()
    bodies = [b.strip() for b in a.bodies.split(",") if b.strip()] or None
    rp = None
    try:
        rp = Replayer(node, rec, a.prefix, a.rate, a.loop, bodies, a.keep_stamps, clock=a.clock, frame=a.frame)
        deadline = time.monotonic() + a.wait_subscribers
        while time.monotonic() < deadline and not any(p.get_subscription_count() for p in rp.pubs.values()):
            time.sleep(0.05)
        log.info(f"replaying {a.recording}: bodies {rec.bodies}, {rec.duration:.1f} s, "
                 f"{rec.rate_hz(rec.bodies[0]):.0f} Hz, speed x{a.rate}")
        freeze_long_lived()  # no full collection walks the start-up's objects while it streams at 120 Hz
        rp.start()
        while rp.running and rclpy.ok():
            rp.join(0.2)
        log.info(f"published {rp.published} poses")
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except ValueError as exc:
        print(f"mocap_replay: error: {exc}", file=sys.stderr)
        return 2
    finally:
        if rp is not None:
            rp.stop()
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
