"""Where a moving target will be, and where it will look, over the next seconds (from its pose stream); which
obstacles turn in place (:class:`TurningWatch`).

A plan takes tens of seconds to execute; judging its views by where the target looks *now* chases a person who turns
back and forth towards views that are gone before the robot gets there. :class:`TargetPredictor` turns a target's
pose stream into a *predictive mixture* for any future instant: a few weighted poses whose spread grows with the
horizon.

* **Position**: the target's velocity, fitted over the last ``rate_window_s`` (least squares), extrapolated with a
  fading rate (time constant ``velocity_decay_s``): a walking person is expected to walk on, a standing one to stay
  (a fitted speed below ``still_mps`` is sway and mocap noise).
* **Heading** (rotation about the vertical): the heading rate, fitted likewise, is extrapolated with a shorter
  fading time (``rate_decay_s``): a turn in progress continues for a moment. Over longer horizons the extrapolation
  gives way, with weight ``exp(-tau / revert_s)``, to the distribution of headings seen over the last
  ``history_s`` (its quantiles, one mixture component each): a person turning side to side is expected to look
  where they have been looking, in the proportion they have, not to keep turning. A target whose heading has not
  changed has a history of one heading, and the mixture collapses to it. A target that walks (faster than
  ``walk_mps``) looks where it goes, not where it looked while standing: its mixture is the extrapolation alone.
* **A turn that repeats** (a person scanning side to side at a steady pace): over the last ``period_window_s`` (the
  headings resampled at 10 Hz), the lag between 2 s and the window over 1.6 that best correlates the heading with
  itself, past the lag where the correlation first turns negative, is the turn's period P when that correlation c
  is at least ``period_min_corr`` (of lags that correlate within 0.02 of the best, the shortest: a turn repeats
  at twice its period too). The heading at t is then predicted to be the one seen k periods earlier (the
  smallest k that reaches back before the latest sample), a component of weight (0.9 c)**k of what the extrapolation
  leaves (each period reached back adds the uncertainty of one more repetition); the history's quantiles share the
  rest. Without such a period (too little history, an irregular turn, a target that does not turn) the mixture is
  as above.

Every component keeps the latest pose's roll and pitch (rotation about the vertical only).

Bad input: a sample with NaN/inf, a time that does not advance, or a jump (faster than ``max_speed_mps`` /
``max_turn_rate``) is discarded with a warning, and the last good pose is used; ``max_rejects`` jumps in a row are
taken as a real relocation (the history restarts there). A gap longer than ``max_gap_s`` restarts the rate fit
(the rates are zero until it has samples again) and the search for a repeating turn.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass
from typing import Optional

import numpy as np

from .errors import InputError
from .geometry import turn_about_z, wrap_angle

log = logging.getLogger(__name__)

PERIOD_STEP_S = 0.1  # the headings' resampling step for a repeating turn
PERIOD_MIN_S = 2.0  # the shortest period looked for
PERIOD_TIE = 0.02  # a multiple of the period correlating within this of the best is not taken for the period
PERIOD_TRUST = 0.9  # a repetition is trusted at most this much (a person never repeats a turn exactly)


@dataclass(frozen=True)
class PredictionSettings:
    """Target motion prediction (``config/planners/replan.yaml``, group ``prediction``)."""

    enabled: bool = True  # off: every prediction is the latest pose (the instantaneous view)
    history_s: float = 20.0  # headings kept for the mixture (a back-and-forth turn should fit in it)
    rate_window_s: float = 0.5  # velocity and heading rate fitted over this
    rate_decay_s: float = 0.8  # the extrapolated heading rate fades with this time constant (s)
    velocity_decay_s: float = 2.0  # the extrapolated velocity fades with this time constant (s): a walk goes on a
    # second or two (people indoors walk short legs; `psprm perf prediction` scores the forecasts)
    revert_s: float = 4.0  # the extrapolated heading gives way to the history's headings with this time constant (s)
    components: int = 3  # mixture poses: the extrapolation and (components - 1) quantiles of the history's headings
    still_mps: float = 0.05  # a fitted speed below this is mocap noise and sway: the target stands
    walk_mps: float = 0.3  # a target faster than this walks: it looks where it goes (no history components); a face
    # turning about its neck moves a few cm/s
    max_speed_mps: float = 4.0  # a target faster than this between two samples jumped: the sample is discarded
    max_turn_rate: float = 10.0  # rad/s, likewise
    max_gap_s: float = 1.0  # a longer gap restarts the rate fit
    max_rejects: int = 30  # this many jumps in a row: a relocation, accepted
    period_window_s: float = 45.0  # headings kept (10 Hz) to find a turn that repeats; 0: no periodic component
    period_min_corr: float = 0.7  # a repeating turn: the heading one period earlier correlates with it this well

    def __post_init__(self):
        for name in ("history_s", "rate_window_s", "rate_decay_s", "velocity_decay_s", "revert_s", "max_speed_mps",
                     "max_turn_rate", "max_gap_s", "still_mps", "walk_mps"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise InputError(f"prediction.{name} must be a positive number, got {v}")
        if self.components < 1 or self.max_rejects < 1:
            raise InputError("prediction.components and prediction.max_rejects must be >= 1")
        if not (math.isfinite(self.period_window_s) and self.period_window_s >= 0):
            raise InputError(f"prediction.period_window_s must be >= 0, got {self.period_window_s}")
        if not (0.0 < self.period_min_corr <= 1.0):
            raise InputError(f"prediction.period_min_corr must be in (0, 1], got {self.period_min_corr}")


def quat_yaw(q: np.ndarray) -> float:
    """Heading (rad) of an [x, y, z, w] orientation: the angle of its rotation about the world's vertical."""
    x, y, z, w = (float(v) for v in q)
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def turned(q: np.ndarray, dyaw: float) -> np.ndarray:
    """The orientation ``q`` [x, y, z, w] turned by ``dyaw`` about the world's vertical."""
    c, s = math.cos(dyaw / 2), math.sin(dyaw / 2)
    x, y, z, w = (float(v) for v in q)
    # (0, 0, s, c) * (x, y, z, w)
    return np.array([c * x - s * y, c * y + s * x, c * z + s * w, c * w - s * z])



class TargetPredictor:
    """The predictive mixture of one target's pose (module docstring). Feed it with :meth:`add`; ask it with
    :meth:`mixture` (an instant) or :meth:`expected_yaw_spread`."""

    def __init__(self, settings: PredictionSettings = PredictionSettings(), name: str = "target"):
        self.settings = settings
        self.name = name
        self._hist: deque = deque()  # (t, yaw) over history_s
        self._recent: deque = deque()  # (t, p(3), yaw_unwrapped) over rate_window_s, for the rates
        self._series: deque = deque()  # (t, yaw_unwrapped) every 0.1 s over period_window_s, for a repeating turn
        self._period_at: Optional[tuple] = None  # (latest resampled stamp, (grid, headings, period, corr) or None)
        self.t_last: Optional[float] = None
        self.p_last: Optional[np.ndarray] = None
        self.q_last: Optional[np.ndarray] = None
        self._yaw_unwrapped = 0.0
        self._rejects = 0
        self.discarded = 0  # samples discarded so far (NaN, time not advancing, jumps)
        self.velocity = np.zeros(3)
        self.yaw_rate = 0.0

    # ---- input -------------------------------------------------------------------------------------------------------
    def add(self, t: float, position, quat) -> bool:
        """A new pose at time ``t`` (s, any clock that only advances). False (with a warning) when it was discarded:
        the last good pose stays in use."""
        p = np.asarray(position, float).reshape(-1)
        q = np.asarray(quat, float).reshape(-1)
        s = self.settings
        if p.shape != (3,) or q.shape != (4,) or not (np.isfinite(p).all() and np.isfinite(q).all()
                                                     and math.isfinite(t)) or np.linalg.norm(q) < 1e-9:
            return self._discard("a pose with NaN/inf or of the wrong shape")
        q = q / np.linalg.norm(q)
        yaw = quat_yaw(q)
        if self.t_last is not None:
            dt = t - self.t_last
            if dt <= 0:
                return self._discard(f"a pose at {t:.3f} s, not after the last one ({self.t_last:.3f} s)")
            dyaw = float(wrap_angle(yaw - quat_yaw(self.q_last)))
            jump = (np.linalg.norm(p - self.p_last) > s.max_speed_mps * dt + 0.02
                    or abs(dyaw) > s.max_turn_rate * dt + 0.05)
            if jump and self._rejects + 1 < s.max_rejects:
                self._rejects += 1
                return self._discard(f"a jump of {np.linalg.norm(p - self.p_last):.2f} m / {abs(dyaw):.2f} rad in "
                                     f"{dt:.3f} s")
            if jump:  # jumped for good: start again there
                log.warning("target %s: relocated (%d jumps in a row): prediction restarts", self.name, s.max_rejects)
                self._hist.clear()
                self._recent.clear()
                self._series.clear()
                self._yaw_unwrapped = yaw
            else:
                if dt > s.max_gap_s:
                    log.warning("target %s: %.2f s without a pose: the rates and the search for a repeating turn "
                                "restart", self.name, dt)
                    self._recent.clear()
                    self._series.clear()
                self._yaw_unwrapped += dyaw
        else:
            self._yaw_unwrapped = yaw
        self._rejects = 0
        self.t_last, self.p_last, self.q_last = float(t), p, q
        self._hist.append((float(t), yaw))
        while self._hist and self._hist[0][0] < t - s.history_s:
            self._hist.popleft()
        if s.period_window_s > 0 and (not self._series or t - self._series[-1][0] >= PERIOD_STEP_S - 1e-9):
            self._series.append((float(t), self._yaw_unwrapped))
            while self._series and self._series[0][0] < t - s.period_window_s:
                self._series.popleft()
        self._recent.append((float(t), p, self._yaw_unwrapped))
        while self._recent and self._recent[0][0] < t - s.rate_window_s:
            self._recent.popleft()
        self._fit_rates()
        return True

    def _discard(self, why: str) -> bool:
        self.discarded += 1
        log.warning("target %s: discarded %s; the last good pose is used", self.name, why)
        return False

    def _fit_rates(self) -> None:
        """Least-squares velocity and heading rate over the recent samples (zero until they span 0.1 s)."""
        if len(self._recent) < 3 or self._recent[-1][0] - self._recent[0][0] < 0.1:
            self.velocity, self.yaw_rate = np.zeros(3), 0.0
            return
        t = np.array([r[0] for r in self._recent])
        t = t - t.mean()
        den = float(t @ t)
        P = np.array([r[1] for r in self._recent])
        Y = np.array([r[2] for r in self._recent])
        self.velocity = (t @ (P - P.mean(0))) / den
        if np.linalg.norm(self.velocity) < self.settings.still_mps:
            self.velocity = np.zeros(3)
        self.yaw_rate = float(t @ (Y - Y.mean())) / den

    # ---- prediction --------------------------------------------------------------------------------------------------
    @property
    def ready(self) -> bool:
        return self.t_last is not None

    def _history_quantiles(self, m: int) -> np.ndarray:
        """``m`` headings at the quantiles (k + 0.5) / m of the headings seen over ``history_s`` (on the circle:
        unwrapped around their circular mean)."""
        yaws = np.array([h[1] for h in self._hist])
        c = math.atan2(float(np.sin(yaws).mean()), float(np.cos(yaws).mean()))
        rel = wrap_angle(yaws - c)
        return c + np.quantile(rel, (np.arange(m) + 0.5) / m)

    def period(self) -> Optional[tuple]:
        """(P, c): the period (s) of a turn that repeats and how well one period predicts the next (the correlation
        of the heading with itself P earlier), or None (module docstring). Found once per resampled heading (every
        0.1 s), not per pose."""
        key = self._series[-1][0] if self._series else None
        if self._period_at is None or self._period_at[0] != key:
            self._period_at = (key, self._find_period())
        found = self._period_at[1]
        return None if found is None else found[2:]

    def _find_period(self) -> Optional[tuple]:
        ser = self._series
        if len(ser) < 2 or ser[-1][0] - ser[0][0] < 2 * PERIOD_MIN_S:
            return None
        ts = np.array([a for a, _ in ser])
        grid = np.arange(ts[0], ts[-1] + 1e-9, PERIOD_STEP_S)
        y = np.interp(grid, ts, np.array([b for _, b in ser]))
        r = y - y.mean()
        if r.std() < 0.1:  # not turning (mocap noise and sway)
            return None
        lags = np.arange(int(round(PERIOD_MIN_S / PERIOD_STEP_S)), int(len(r) / 1.6))
        if len(lags) == 0:
            return None
        cross = np.correlate(r, r, "full")[len(r) - 1 + lags]  # sum of r[L:] * r[:-L] per lag L
        e = np.concatenate([[0.0], np.cumsum(r * r)])
        head, tail = e[len(r) - lags], e[-1] - e[lags]  # energies of r[:-L] and r[L:]
        corr = cross / np.maximum(1e-12, np.sqrt(head * tail))
        neg = np.flatnonzero(corr < 0)
        if len(neg) == 0:  # no turn back within the window
            return None
        after = corr[neg[0]:]
        best = float(after.max())
        if best < self.settings.period_min_corr:
            return None
        # the shortest lag that correlates about as well as the best: a turn that repeats every P also repeats
        # every 2P, and a turn that dwells at each side correlates as well (to rounding) at both
        i = neg[0] + int(np.flatnonzero(after >= best - PERIOD_TIE)[0])
        while i + 1 < len(corr) and corr[i + 1] > corr[i]:  # up to that peak's top
            i += 1
        return grid, y, float(lags[i] * PERIOD_STEP_S), float(corr[i])

    def _periodic_yaw(self, t: float) -> Optional[tuple]:
        """(weight (0.9 c)**k, heading) of the periodic component at ``t`` (module docstring), or None."""
        if self.period() is None:
            return None
        grid, y, P, c = self._period_at[1]
        k = max(1, math.ceil((t - self.t_last) / P - 1e-9))
        u = t - k * P
        if u < grid[0]:
            return None
        return (c * PERIOD_TRUST) ** k, float(np.interp(u, grid, y))

    def mixture(self, t: float) -> list:
        """The predicted pose at time ``t`` as [(weight, position (3,), quat (4,)), ...], weights summing to 1. At or
        before the latest sample, and with prediction off, the latest pose alone."""
        if not self.ready:
            raise InputError(f"target {self.name}: no pose yet")
        s = self.settings
        tau = max(0.0, float(t) - self.t_last)
        if not s.enabled or tau == 0.0:
            return [(1.0, self.p_last.copy(), self.q_last.copy())]
        p = self.p_last + self.velocity * s.velocity_decay_s * (1.0 - math.exp(-tau / s.velocity_decay_s))
        yaw_now = quat_yaw(self.q_last)
        dyaw_e = self.yaw_rate * s.rate_decay_s * (1.0 - math.exp(-tau / s.rate_decay_s))
        out = [(1.0, p, turned(self.q_last, dyaw_e))]
        m = s.components - 1
        walking = bool(np.linalg.norm(self.velocity) > s.walk_mps)
        if m > 0 and len(self._hist) > 1 and not walking:
            w_e = math.exp(-tau / s.revert_s)
            out, rest = [(w_e, p, out[0][2])], 1.0 - w_e
            periodic = self._periodic_yaw(t)
            if periodic is not None:
                out.append((rest * periodic[0], p, turned(self.q_last, float(wrap_angle(periodic[1] - yaw_now)))))
                rest *= 1.0 - periodic[0]
            for y in self._history_quantiles(m):
                out.append((rest / m, p, turned(self.q_last, float(wrap_angle(y - yaw_now)))))
        return out

    def expected_yaw_spread(self, t: float) -> float:
        """The mixture's heading spread (rad, weighted standard deviation about its circular mean) at ``t``: the
        prediction's uncertainty, growing with the horizon from 0 to the history's spread."""
        mix = self.mixture(t)
        yaws = np.array([quat_yaw(q) for _, _, q in mix])
        w = np.array([w for w, _, _ in mix])
        c = math.atan2(float(w @ np.sin(yaws)), float(w @ np.cos(yaws)))
        return float(math.sqrt(max(0.0, float(w @ wrap_angle(yaws - c) ** 2))))


class TurningWatch:
    """Which obstacles are turning in place: a person's body that turns about its vertical axis sweeps a disc, and a
    robot that passes or rests beside it at its current heading is hit by its next turn.

    A body turns in place when its heading (about its own z axis) moves by more than ``turn_rad`` from an anchor pose
    while its centre stays within ``in_place_m`` of the anchor's; the anchor is its first pose, moved to the latest
    one after each such turn and whenever the centre leaves that radius (a walking person, or a chair carried
    elsewhere and set down at another heading, has not turned in place). It counts as turning until ``hold_s`` have
    passed without another turn: a nurse who turns to the bed every ten seconds stays turning, a chair turned once
    does not for long. Stamps are the caller's clock (seconds), one clock per body."""

    def __init__(self, turn_rad: float, hold_s: float, in_place_m: float):
        self.turn_rad, self.hold_s, self.in_place_m = float(turn_rad), float(hold_s), float(in_place_m)
        self._anchor: dict = {}  # name -> (centre (3,), quat (4,))
        self._last_turn: dict = {}  # name -> stamp of the latest turn in place

    def update(self, name: str, center, quat, stamp: float) -> bool:
        """A new pose of body ``name`` at ``stamp``; whether it is turning now."""
        c, q = np.asarray(center, float), np.asarray(quat, float)
        anchor = self._anchor.get(name)
        if anchor is None or np.linalg.norm(c[:2] - anchor[0][:2]) > self.in_place_m:
            self._anchor[name] = (c.copy(), q.copy())
        elif turn_about_z(anchor[1], q) > self.turn_rad:
            self._anchor[name] = (anchor[0], q.copy())
            self._last_turn[name] = stamp
        last = self._last_turn.get(name)
        return last is not None and stamp - last <= self.hold_s
