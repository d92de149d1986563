"""Lifecycle, diagnostics and watchdog helpers of the psprm ROS 2 nodes: a lifecycle node whose transitions call its
owner's ``on_configure`` ... ``on_shutdown``, autostart, ``/diagnostics`` statuses, and the stall grace of a periodic
watchdog. rclpy and the message packages are imported inside the functions that need them."""

from __future__ import annotations

import time
from typing import Optional


# ---------------------------------------------------------------------------------------------------------- lifecycle
def lifecycle_node(owner, node_name: str, **node_kwargs):
    """An ``rclpy.lifecycle.LifecycleNode`` whose transitions call ``owner.on_configure(state)``,
    ``on_activate``, ``on_deactivate``, ``on_cleanup``, ``on_shutdown`` (those the owner has). A callback returning
    False fails the transition; one raising is reported (log, ``owner.status``, and for a configure
    ``owner.set_state("error: ...")`` where the owner has one) and fails it too (the node stays usable).
    ``node.refuse_configure(reason)`` makes every configure fail with ``reason``, reported the same way, without
    calling the owner."""
    from rclpy.lifecycle import LifecycleNode, TransitionCallbackReturn

    def failed(name, text):
        node.get_logger().error(f"{name[3:]} failed: {text}")
        status = getattr(owner, "status", None)
        if status is not None:
            try:
                status(f"{name[3:]} failed: {text}", "error")
            except Exception:
                pass
        set_state = getattr(owner, "set_state", None)  # the roadmap server's latched state
        if name == "on_configure" and set_state is not None:
            try:
                set_state(f"error: {text}")
            except Exception:
                pass

    def call(name, state):
        if name == "on_configure" and node.configure_refusal:
            failed(name, node.configure_refusal)
            return TransitionCallbackReturn.FAILURE
        fn = getattr(owner, name, None)
        if fn is None:
            return TransitionCallbackReturn.SUCCESS
        try:
            ok = fn(state)
        except Exception as exc:  # a configuration error: the transition fails, the node lives on
            failed(name, exc)
            return TransitionCallbackReturn.FAILURE
        if name == "on_configure":
            for text in bare_setting_names(node):
                node.get_logger().warning(text)
        return TransitionCallbackReturn.FAILURE if ok is False else TransitionCallbackReturn.SUCCESS

    class _Managed(LifecycleNode):
        #: why this node cannot be configured (set at construction, e.g. parameter values it refused): every
        #: configure then fails with it, so the node never activates
        configure_refusal: str = ""

        def refuse_configure(self, reason: str) -> None:
            self.configure_refusal = str(reason)

        def on_configure(self, state):
            return call("on_configure", state)

        def on_activate(self, state):
            r = call("on_activate", state)
            if r == TransitionCallbackReturn.SUCCESS:
                super().on_activate(state)  # lifecycle publishers follow
            return r

        def on_deactivate(self, state):
            r = call("on_deactivate", state)
            if r == TransitionCallbackReturn.SUCCESS:
                super().on_deactivate(state)
            return r

        def on_cleanup(self, state):
            return call("on_cleanup", state)

        def on_shutdown(self, state):
            return call("on_shutdown", state)

        def on_error(self, state):
            return call("on_error", state)

    node = _Managed(node_name, **node_kwargs)
    return node


def bare_setting_names(node) -> list:
    """Warnings for the parameters ``node`` was given (params file, ``-p``) under a bare name that it declares only
    under a dotted one (``alpha`` for ``scoring.alpha``): rclpy ignores a parameter that is not declared, so the
    value would silently not apply. Names shared by every node (the ``/**`` section) that this node does not
    declare at all are left alone."""
    given = getattr(node, "_parameter_overrides", None) or {}  # rclpy keeps the node's overrides there
    declared = list(node.list_parameters([], 0).names)  # depth 0: every name, dotted ones included
    out = []
    for name in sorted(given):
        if "." in name or node.has_parameter(name):
            continue
        full = [d for d in declared if d.endswith("." + name)]
        if len(full) == 1:
            out.append(f"parameter '{name}' is not a parameter of {node.get_name()}; the setting is "
                       f"'{full[0]}' (ignored)")
    return out


def lifecycle_state(node) -> str:
    """Label of a lifecycle node's current state (``unconfigured``, ``inactive``, ``active``, ``finalized``)."""
    try:
        return node._state_machine.current_state[1]
    except Exception:
        return "unknown"


def autostart(owner) -> bool:
    """Configure then activate ``owner.node`` (what a lifecycle manager with autostart does); True when active."""
    from rclpy.lifecycle import TransitionCallbackReturn

    n = owner.node
    if lifecycle_state(n) == "unconfigured" and n.trigger_configure() != TransitionCallbackReturn.SUCCESS:
        return False
    if lifecycle_state(n) == "inactive" and n.trigger_activate() != TransitionCallbackReturn.SUCCESS:
        return False
    return lifecycle_state(n) == "active"


# ---------------------------------------------------------------------------------------------------------- diagnostics
DIAG_OK, DIAG_WARN, DIAG_ERROR, DIAG_STALE = 0, 1, 2, 3
DIAGNOSTICS_TOPIC = "/diagnostics"


def diagnostic_status(name: str, hardware_id: str, level: int, message: str, values: dict):
    """``diagnostic_msgs/DiagnosticStatus`` with ``values`` as key/value strings (floats rounded)."""
    from diagnostic_msgs.msg import DiagnosticStatus, KeyValue

    s = DiagnosticStatus()
    s.level = bytes([int(level)])
    s.name, s.hardware_id, s.message = name, hardware_id, message
    kv = []
    for k, v in values.items():
        if isinstance(v, float):
            v = f"{v:.4g}"
        kv.append(KeyValue(key=str(k), value=str(v)))
    s.values = kv
    return s


def publish_diagnostics(pub, node, statuses: list) -> None:
    from diagnostic_msgs.msg import DiagnosticArray

    a = DiagnosticArray()
    a.header.stamp = node.get_clock().now().to_msg()
    a.status = list(statuses)
    try:
        pub.publish(a)
    except Exception:  # shutting down
        pass


# ---------------------------------------------------------------------------------------------------------- watchdogs
class StallGrace:
    """Keeps a periodic watchdog from blaming its inputs for a stall of its own process.

    When a watchdog step runs late (more than ``late_periods`` periods after the previous one: a collection, another
    thread holding the interpreter, the process not scheduled), the messages that arrived meanwhile may still wait in
    the node's queue, so an input that looks stale may only be queued. :meth:`forgive` then puts the verdict off by
    one step; a stale verdict at the next step stands (forgiven once per stall, never twice in a row)::

        late = grace.step()                    # at every watchdog step
        if stale and grace.forgive(late):      # decide at the next step
            return
        ...
        grace.clear()                          # when the inputs are fresh
    """

    def __init__(self, period_s: float, late_periods: float = 3.0):
        self.period_s, self.late_periods = float(period_s), float(late_periods)
        self._last = -1.0  # monotonic time of the previous step
        self._used = False  # a stale verdict was put off and no fresh step followed yet

    def step(self, now: Optional[float] = None) -> bool:
        """Record a watchdog step; True when it runs late."""
        now = time.monotonic() if now is None else now
        late = self._last > 0 and now - self._last > self.late_periods * self.period_s
        self._last = now
        return late

    def forgive(self, late: bool) -> bool:
        """True when a stale verdict of this (``late``) step is to be put off."""
        if late and not self._used:
            self._used = True
            return True
        return False

    def clear(self) -> None:
        """The inputs were fresh at this step: a later stall is forgiven again."""
        self._used = False
