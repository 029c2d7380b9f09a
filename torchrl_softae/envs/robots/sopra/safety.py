"""Safety layer between any controller and SoPrA's valves, independent of the backend.

Every pressure command is clipped to [0, p_max] and rate-limited (at most ``max_rate`` mbar of
change per command, except venting, which drops to zero at once). A fault -- a stale, lost or
out-of-workspace motion-capture frame, a non-finite command, an exception from the valves --
vents all chambers and raises :class:`SafetyFault`. The layer also vents on ``close()``, on
SIGINT and at interpreter exit. ``dry_run=True`` swaps the valves for a recorder: motion capture
is real, nothing is ever sent to the valves.
"""
from __future__ import annotations

import atexit
import logging
import signal
import threading
from dataclasses import dataclass

import numpy as np

from torchrl_softae.envs.robots.sopra.backends import N_CHAMBERS, Pose, RecordingValveArray, ValveArray

__all__ = ["SafetyLimits", "SafetyFault", "SafetyLayer"]

LOG = logging.getLogger("torchrl_softae.sopra")


@dataclass
class SafetyLimits:
    """Conservative defaults: DragonSkin 10 (400 mbar cap); raise p_max to 1200 only for DragonSkin 30."""

    p_max: float = 400.0  # [mbar]
    max_rate: float = 50.0  # [mbar] per command
    stale_factor: float = 3.0  # stale: no new frame within stale_factor x control period
    workspace_low: tuple = (-0.25, -0.25, -0.30)  # tip position relative to the base ring [m]
    workspace_high: tuple = (0.25, 0.25, 0.02)

    def __post_init__(self):
        if not (self.p_max > 0 and np.isfinite(self.p_max)):
            raise ValueError(f"SafetyLimits: p_max={self.p_max!r} mbar, expected a finite value > 0")
        if not (self.max_rate > 0 and np.isfinite(self.max_rate)):
            raise ValueError(f"SafetyLimits: max_rate={self.max_rate!r} mbar/step, expected a finite value > 0")
        if not self.stale_factor >= 1:
            raise ValueError(f"SafetyLimits: stale_factor={self.stale_factor!r}, expected >= 1")
        if np.any(np.asarray(self.workspace_low) >= np.asarray(self.workspace_high)):
            raise ValueError(f"SafetyLimits: workspace_low {self.workspace_low} must be below workspace_high {self.workspace_high}")


class SafetyFault(RuntimeError):
    """The safety layer vented the arm; the message says why."""


class SafetyLayer:
    def __init__(self, valves: ValveArray, limits: SafetyLimits | None = None, control_period: float = 0.1,
                 dry_run: bool = False, install_handlers: bool = True):
        self.limits = limits or SafetyLimits()
        self.control_period = control_period
        self.dry_run = dry_run
        self.valves = RecordingValveArray() if dry_run else valves
        self.last_command = np.zeros(N_CHAMBERS)
        self.faults: list[str] = []
        self.vent_count = 0
        self._last_frame = (-1, float("-inf"))  # (frame number, time it was first seen)
        self._closed = False
        self._prev_sigint = None
        if install_handlers:
            atexit.register(self._vent_at_exit)
            if threading.current_thread() is threading.main_thread():
                self._prev_sigint = signal.getsignal(signal.SIGINT)
                signal.signal(signal.SIGINT, self._on_sigint)

    # ------------------------------------------------------------------ commands
    def command(self, target_mbar) -> np.ndarray:
        """Clip, rate-limit and send; returns what was sent."""
        target = np.asarray(target_mbar, dtype=np.float64).reshape(-1)
        if target.shape != (N_CHAMBERS,) or not np.all(np.isfinite(target)):
            self.fault(f"invalid pressure command {target!r} (expected 6 finite values)")
        lim = self.limits
        clipped = np.clip(target, 0.0, lim.p_max)
        step = np.clip(clipped - self.last_command, -lim.max_rate, lim.max_rate)
        sent = np.clip(self.last_command + step, 0.0, lim.p_max)
        try:
            self.valves.send_pressures(sent)
        except Exception as e:  # noqa: BLE001
            self.fault(f"valve array raised {type(e).__name__}: {e}")
        self.last_command = sent
        return sent

    def vent(self, reason: str = "vent requested") -> None:
        self.vent_count += 1
        self.last_command = np.zeros(N_CHAMBERS)
        try:
            self.valves.vent()
        except Exception as e:  # noqa: BLE001  (venting must never raise: log loudly)
            LOG.error("venting failed (%s: %s) after: %s -- CHECK THE ARM", type(e).__name__, e, reason)

    def fault(self, reason: str):
        """Vent, record and raise."""
        self.faults.append(reason)
        LOG.warning("SoPrA safety fault: %s -> venting", reason)
        self.vent(reason)
        raise SafetyFault(reason)

    # ------------------------------------------------------------------ motion capture checks
    def check_frame(self, frame_number: int, poses: dict[str, Pose], now: float, tip_relative=None) -> None:
        """Fault on a stale frame (no new frame number for stale_factor x control period),
        a lost (NaN) body, or a tip outside the workspace box."""
        if frame_number != self._last_frame[0]:
            self._last_frame = (frame_number, now)
        stale_after = self.limits.stale_factor * self.control_period
        if frame_number < 0 or now - self._last_frame[1] > stale_after:
            self.fault(f"motion capture is stale: no new frame for more than {stale_after:.3f} s")
        lost = [name for name, p in poses.items() if not p.valid]
        if lost:
            self.fault(f"motion capture lost bodies {lost}")
        if tip_relative is not None:
            lo, hi = np.asarray(self.limits.workspace_low), np.asarray(self.limits.workspace_high)
            if np.any(tip_relative < lo) or np.any(tip_relative > hi):
                self.fault(f"tip {np.round(tip_relative, 4).tolist()} left the workspace box {lo.tolist()}..{hi.tolist()}")

    def reset_watchdog(self) -> None:
        self._last_frame = (-1, float("-inf"))

    # ------------------------------------------------------------------ shutdown
    def _on_sigint(self, signum, frame):
        self.vent("SIGINT")
        prev = self._prev_sigint
        if callable(prev):
            prev(signum, frame)
        else:
            raise KeyboardInterrupt

    def _vent_at_exit(self):
        if not self._closed:
            self.vent("interpreter exit")

    def close(self) -> None:
        if self._closed:
            return
        self.vent("close")
        self._closed = True
        atexit.unregister(self._vent_at_exit)
        if self._prev_sigint is not None and threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, self._prev_sigint)
            self._prev_sigint = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False
