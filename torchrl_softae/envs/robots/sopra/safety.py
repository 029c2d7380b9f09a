"""Safety layer between any controller and SoPrA's valves, independent of the backend.

What it guarantees, whatever the caller does:

* **Range and rate.** Every pressure sent is in [0, p_max] and differs from the previous one by at
  most ``max_rate`` mbar per chamber; only venting (all zeros) may drop faster.
* **Faults latch.** A fault -- a stale, lost or out-of-workspace motion-capture frame, a
  non-finite or malformed command, a valve or motion-capture error or timeout, the watchdog --
  vents all chambers and latches: :meth:`SafetyLayer.command` then refuses (raises
  :class:`SafetyFault`, sends nothing) until :meth:`SafetyLayer.rearm`, which the env calls only in
  ``reset`` after venting and settling. After :meth:`SafetyLayer.close` nothing is ever sent again
  but vents.
* **Dead-man's switch.** A watchdog thread, armed by the first command of an episode, vents and
  latches a fault when no new command arrives within ``watchdog_periods`` control periods (a
  hung planner, a blocked process, a dead control thread) or when the motion-capture stream
  delivers no new frame within the stale window, even if nobody calls :meth:`check_frame`. It is
  disarmed at episode end (:meth:`end_episode`, which also vents), at close and while idle.
* **One transaction at a time.** Commands, vents and the watchdog share one lock: a watchdog
  vent never interleaves with a command on the bus.

It also vents on SIGINT and at interpreter exit. Nothing in this process can act after
``kill -9``: that is the valve terminal's own communication watchdog's job (README, "Running on a
real SoPrA"). ``dry_run=True`` swaps the valves for a recorder: motion capture is real, nothing is
ever sent to the valves.
"""
from __future__ import annotations

import atexit
import logging
import signal
import threading
import time
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
    watchdog_periods: float = 3.0  # vent when no command arrives within this many control periods

    def __post_init__(self):
        if not (self.p_max > 0 and np.isfinite(self.p_max)):
            raise ValueError(f"SafetyLimits: p_max={self.p_max!r} mbar, expected a finite value > 0")
        if not (self.max_rate > 0 and np.isfinite(self.max_rate)):
            raise ValueError(f"SafetyLimits: max_rate={self.max_rate!r} mbar/step, expected a finite value > 0")
        if not self.stale_factor >= 1:
            raise ValueError(f"SafetyLimits: stale_factor={self.stale_factor!r}, expected >= 1")
        if not (self.watchdog_periods >= 1 and np.isfinite(self.watchdog_periods)):
            raise ValueError(f"SafetyLimits: watchdog_periods={self.watchdog_periods!r}, expected a finite value >= 1")
        if np.any(np.asarray(self.workspace_low) >= np.asarray(self.workspace_high)):
            raise ValueError(f"SafetyLimits: workspace_low {self.workspace_low} must be below workspace_high {self.workspace_high}")


class SafetyFault(RuntimeError):
    """The safety layer vented the arm (or refuses to command it); the message says why."""


class SafetyLayer:
    """Clips, rate-limits, latches faults and watches the controller (see the module docstring).

    Args:
        valves: the valve array (``send_pressures``, ``vent``).
        limits: pressure cap, rate limit, staleness, workspace box, watchdog window.
        control_period: seconds per control step (the watchdog's and the stale check's unit).
        dry_run: replace the valves by a :class:`RecordingValveArray`.
        install_handlers: vent on SIGINT and at interpreter exit.
        watchdog: run the dead-man's switch (wall-clock time).
        frame_source: ``() -> (frame number, poses)`` (the motion capture's ``latest``), so the
            watchdog notices a stream that stopped.
    """

    def __init__(self, valves: ValveArray, limits: SafetyLimits | None = None, control_period: float = 0.1,
                 dry_run: bool = False, install_handlers: bool = True, watchdog: bool = True, frame_source=None):
        if not control_period > 0:
            raise ValueError(f"SafetyLayer: control_period={control_period!r} s, expected > 0")
        self.limits = limits or SafetyLimits()
        self.control_period = control_period
        self.dry_run = dry_run
        self.valves = RecordingValveArray() if dry_run else valves
        self.last_command = np.zeros(N_CHAMBERS)
        self.faults: list[str] = []
        self.vent_count = 0
        self.watchdog_trips: list[float] = []  # wall-clock latency (s) from the last command to each watchdog vent
        self._bus = threading.RLock()  # one valve transaction at a time (commands, vents, watchdog)
        self._latched: str | None = None
        self._closed = False
        self._armed = False
        self._last_command_wall = 0.0
        self._last_frame = (-1, float("-inf"))  # (frame number, time it was first seen), caller's clock
        self._frame_source = frame_source
        self._seen_frame = (None, 0.0)  # the watchdog's own (frame number, wall time first seen)
        self._stop = threading.Event()
        self._watchdog_thread = None
        if watchdog:
            self._watchdog_thread = threading.Thread(target=self._watch, name="sopra-watchdog", daemon=True)
            self._watchdog_thread.start()
        self._prev_sigint = None
        if install_handlers:
            atexit.register(self._vent_at_exit)
            if threading.current_thread() is threading.main_thread():
                self._prev_sigint = signal.getsignal(signal.SIGINT)
                signal.signal(signal.SIGINT, self._on_sigint)

    # ------------------------------------------------------------------ state
    @property
    def latched(self) -> str | None:
        """The reason of the latched fault, or ``None`` when commands are accepted."""
        return "closed" if self._closed else self._latched

    @property
    def armed(self) -> bool:
        """Whether the watchdog is watching (between the first command of an episode and its end)."""
        return self._armed

    @property
    def watchdog_window(self) -> float:
        return self.limits.watchdog_periods * self.control_period

    # ------------------------------------------------------------------ commands
    def command(self, target_mbar) -> np.ndarray:
        """Clip, rate-limit and send; returns what was sent. Raises :class:`SafetyFault` (and sends
        nothing) while a fault is latched or after close; arms the watchdog."""
        with self._bus:
            if self._closed:
                raise SafetyFault("the safety layer is closed: no command reaches the valves any more")
            if self._latched is not None:
                raise SafetyFault(f"latched after a fault ({self._latched}): reset the env to vent, settle and re-arm")
            target = np.asarray(target_mbar, dtype=np.float64).reshape(-1)
            if target.shape != (N_CHAMBERS,) or not np.all(np.isfinite(target)):
                self.fault(f"invalid pressure command {target!r} (expected 6 finite values)")
            lim = self.limits
            clipped = np.clip(target, 0.0, lim.p_max)
            step = np.clip(clipped - self.last_command, -lim.max_rate, lim.max_rate)
            sent = np.clip(self.last_command + step, 0.0, lim.p_max)
            try:
                self.valves.send_pressures(sent)
            except Exception as e:  # noqa: BLE001 -- includes I/O timeouts
                self.fault(f"valve array raised {type(e).__name__}: {e}")
            self.last_command = sent
            self._last_command_wall = time.monotonic()
            if not self._armed:
                self._seen_frame = (None, self._last_command_wall)
                self._armed = True
            return sent

    def vent(self, reason: str = "vent requested") -> None:
        """All chambers to zero; always allowed, never raises (a failed vent is logged loudly)."""
        with self._bus:
            self.vent_count += 1
            self.last_command = np.zeros(N_CHAMBERS)
            try:
                self.valves.vent()
            except Exception as e:  # noqa: BLE001
                LOG.error("venting failed (%s: %s) after: %s -- CHECK THE ARM", type(e).__name__, e, reason)

    def fault(self, reason: str):
        """Vent, latch, record and raise :class:`SafetyFault`."""
        with self._bus:
            self._latch(reason)
        raise SafetyFault(reason)

    def _latch(self, reason: str) -> None:
        self.faults.append(reason)
        LOG.warning("SoPrA safety fault: %s -> venting", reason)
        self.vent(reason)
        self._latched = reason
        self._armed = False

    def end_episode(self) -> None:
        """Vent and disarm the watchdog (the episode is over; the caller may now think for long)."""
        with self._bus:
            self._armed = False
            self.vent("episode end")

    def rearm(self) -> None:
        """Accept commands again after a fault. The env calls it in ``reset``, after venting and
        settling; a closed layer cannot be re-armed."""
        with self._bus:
            if self._closed:
                raise SafetyFault("the safety layer is closed: it cannot be re-armed")
            self.vent("re-arm")
            self._latched = None
            self._armed = False
            self._last_frame = (-1, float("-inf"))

    # ------------------------------------------------------------------ the watchdog
    def _watch(self) -> None:
        poll = min(self.control_period / 10, 0.01)
        while not self._stop.wait(poll):
            if not self._armed:
                continue
            with self._bus:
                if not self._armed or self._closed:
                    continue
                now = time.monotonic()
                reason = None
                silent = now - self._last_command_wall
                if silent > self.watchdog_window:
                    reason = (f"watchdog: no command for {silent:.3f} s (window {self.watchdog_window:.3f} s): "
                              "the controller stalled")
                elif self._frame_source is not None:
                    reason = self._frame_age_fault(now)
                if reason is not None:
                    self.watchdog_trips.append(silent)
                    self._latch(reason)

    def _frame_age_fault(self, now: float) -> str | None:
        try:
            number = self._frame_source()[0]
        except Exception as e:  # noqa: BLE001
            return f"watchdog: motion capture raised {type(e).__name__}: {e}"
        if number != self._seen_frame[0]:
            self._seen_frame = (number, now)
            return None
        stale_after = self.limits.stale_factor * self.control_period
        if now - self._seen_frame[1] > stale_after:
            return f"watchdog: motion capture delivered no new frame for more than {stale_after:.3f} s"
        return None

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
        """Forget the last frame (the stale check restarts)."""
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
        """Vent, stop the watchdog and refuse every later command."""
        with self._bus:
            if self._closed:
                return
            self.vent("close")
            self._closed = True
            self._armed = False
        self._stop.set()
        if self._watchdog_thread is not None and self._watchdog_thread is not threading.current_thread():
            self._watchdog_thread.join(timeout=1.0)
        atexit.unregister(self._vent_at_exit)
        if self._prev_sigint is not None and threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, self._prev_sigint)
            self._prev_sigint = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False
