"""``SoPrAEnv``: the pneumatic soft arm as a TorchRL env, on hardware or on its simulated twin.

State (Table S4, 32D; poses relative to the base ring, velocities from filtered finite
differences over capture timestamps): tip position 0:3, tip quaternion 3:7, midpoint position
7:10, midpoint quaternion 10:14, tip linear 14:17 and angular 17:20 velocity, midpoint linear
20:23 and angular 23:26 velocity, previous commanded pressures / p_max 26:32.
Action: six pressure deltas in [-1, 1] times ``max_step`` mbar, added to the previous command,
then clipped and rate-limited by the :class:`SafetyLayer`.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from torchrl_softae.envs.robots.rotations import quat_conj as _qconj, quat_mul as _qmul, quat_rotate as _qrot
from torchrl_softae.envs.robots.sopra.backends import N_CHAMBERS, Pose
from torchrl_softae.envs.robots.sopra.safety import SafetyFault, SafetyLayer, SafetyLimits

__all__ = ["SoPrAEnv", "MonotonicClock", "sopra_layout", "SOPRA_TARGETS", "SOPRA_TARGET_PRESSURES"]


def sopra_layout() -> dict[str, slice]:
    return {"tip_position": slice(0, 3), "tip_orientation": slice(3, 7), "mid_position": slice(7, 10),
            "mid_orientation": slice(10, 14), "tip_velocity": slice(14, 17), "tip_angular_velocity": slice(17, 20),
            "mid_velocity": slice(20, 23), "mid_angular_velocity": slice(23, 26), "previous_pressures": slice(26, 32)}


# Tasks (ix) close and (x) far: settled twin tips under constant pressures (reachable by
# construction; within the default 400 mbar cap).
SOPRA_TARGET_PRESSURES = {
    "reach-close": np.array([150.0, 0, 0, 0, 0, 0]),
    "reach-far": np.array([0, 400.0, 0, 0, 400.0, 0]),
}
SOPRA_TARGETS = {  # the default twin's settled tips under those pressures (checked in the tests)
    "reach-close": np.array([-0.0095, 0.0, -0.2520]),
    "reach-far": np.array([0.0204, 0.0353, -0.2468]),
}


class MonotonicClock:
    """Wall clock for hardware: ``now`` is ``time.monotonic``; ``sleep_until`` sleeps."""

    def now(self) -> float:
        return time.monotonic()

    def sleep_until(self, t: float) -> None:
        dt = t - time.monotonic()
        if dt > 0:
            time.sleep(dt)


@dataclass
class _Relative:
    position: np.ndarray
    quaternion: np.ndarray
    timestamp: float


class SoPrAEnv(EnvBase):
    """SoPrA as a TorchRL env.

    Args:
        backend: ``"sim"`` (the twin, default), ``"hardware"`` (Qualisys + Modbus; pass
            ``qualisys=dict(host=..., bodies=...)`` and ``modbus="valves.yaml"``), or a tuple
            ``(motion_capture, valves, clock)`` of objects speaking the protocols.
        limits (SafetyLimits): pressure cap, rate limit, staleness, workspace box.
        control_period (float): seconds per step. Default 0.1.
        max_step (float): mbar per unit action. Default ``limits.max_rate``.
        dry_run (bool): motion capture only; the valves are never written.
        task: ``"reach-close"`` (ix), ``"reach-far"`` (x), ``"reach-random"`` or ``None``.
        max_steps (int): truncation. Default 200 (exploration; tasks use 20).
        velocity_filter (float): exponential smoothing of finite-difference velocities (0 = none).
        watchdog (bool, optional): the safety layer's dead-man's switch (vent when no command
            arrives within ``limits.watchdog_periods`` control periods of wall-clock time, or when
            motion capture stops). Default: on for hardware, off for the twin, whose simulated
            time stands still while the controller thinks.

    Every episode ends vented (terminal or truncated, before ``step`` returns); a fault latches
    the safety layer until the next ``reset`` vents, settles and re-arms it.
    """

    def __init__(self, backend="sim", *, limits: SafetyLimits | None = None, control_period: float = 0.1,
                 max_step: float | None = None, dry_run: bool = False, task: str | None = None, target=None,
                 max_steps: int = 200, velocity_filter: float = 0.5, settle_speed: float = 0.01,
                 settle_timeout: float = 10.0, seed: int = 0, qualisys: dict | None = None, modbus=None,
                 twin_params=None, install_signal_handlers: bool = True, watchdog: bool | None = None):
        super().__init__(batch_size=[])
        if task not in (None, "reach-close", "reach-far", "reach-random"):
            raise ValueError(f"SoPrAEnv: task={task!r}; valid: reach-close, reach-far, reach-random, None")
        self.limits = limits or SafetyLimits()
        self.control_period = control_period
        self.max_step = float(max_step if max_step is not None else self.limits.max_rate)
        self.task, self.max_steps = task, max_steps
        self.velocity_filter, self.settle_speed, self.settle_timeout = velocity_filter, settle_speed, settle_timeout
        self._rng = np.random.default_rng(seed)
        self.twin = None
        if backend == "sim":
            from torchrl_softae.envs.robots.sopra.sim import SoPrASim

            self.twin = SoPrASim(twin_params, seed=seed)
            mocap, valves, clock = self.twin, self.twin, self.twin
        elif backend == "hardware":
            from torchrl_softae.envs.robots.sopra.backends import ModbusValveArray, QualisysMotionCapture

            mocap = QualisysMotionCapture(**(qualisys or {}))
            valves = None if dry_run else ModbusValveArray(modbus)
            clock = MonotonicClock()
        elif isinstance(backend, tuple) and len(backend) == 3:
            mocap, valves, clock = backend
        else:
            raise ValueError(f"SoPrAEnv: backend={backend!r}; expected 'sim', 'hardware' or (mocap, valves, clock)")
        self.mocap, self.clock = mocap, clock
        self.mocap.start()
        self.safety = SafetyLayer(valves, self.limits, control_period, dry_run=dry_run,
                                  install_handlers=install_signal_handlers,
                                  watchdog=(backend != "sim") if watchdog is None else bool(watchdog),
                                  frame_source=self.mocap.latest)
        self._fixed_target = None if target is None else np.asarray(target, dtype=np.float64)
        self.target = self._task_target()
        self.observation_spec = Composite(
            observation=Unbounded((32,)), overrun=Categorical(2, (1,), dtype=torch.bool),
            safety_fault=Categorical(2, (1,), dtype=torch.bool),
        )
        self.action_spec = Bounded(-1.0, 1.0, (N_CHAMBERS,))
        self.reward_spec = Unbounded((1,))
        self.full_done_spec = Composite(
            done=Categorical(2, (1,), dtype=torch.bool), terminated=Categorical(2, (1,), dtype=torch.bool),
            truncated=Categorical(2, (1,), dtype=torch.bool),
        )
        self.timing = {"periods": [], "overruns": 0, "steps": 0}
        self._last_wall = None

    # ------------------------------------------------------------------ helpers
    def _task_target(self):
        if self._fixed_target is not None:
            return self._fixed_target.copy()
        if self.task in SOPRA_TARGETS:
            return SOPRA_TARGETS[self.task].copy()
        return np.array([0.0, 0.0, -0.25])

    def _relative(self, poses: dict[str, Pose]) -> dict[str, _Relative]:
        base = poses["base"]
        qb = base.quaternion if self._base_ref is None else self._base_ref.quaternion
        pb = base.position if self._base_ref is None else self._base_ref.position
        inv = _qconj(qb)
        return {name: _Relative(_qrot(inv, poses[name].position - pb), _qmul(inv, poses[name].quaternion),
                                poses[name].timestamp) for name in ("mid", "tip")}

    def _velocities(self, rel: dict[str, _Relative]):
        out = {}
        for name, r in rel.items():
            prev = self._prev_rel.get(name)
            if prev is None or r.timestamp <= prev.timestamp:
                lin, ang = self._vel.get(name, (np.zeros(3), np.zeros(3)))
            else:
                dt = r.timestamp - prev.timestamp
                lin_raw = (r.position - prev.position) / dt
                dq = _qmul(_qconj(prev.quaternion), r.quaternion)
                dq = dq if dq[0] >= 0 else -dq
                ang_raw = _qrot(r.quaternion, 2.0 * dq[1:] / dt)  # body rate, expressed in the base frame
                a = self.velocity_filter
                old_lin, old_ang = self._vel.get(name, (lin_raw, ang_raw))
                lin, ang = a * old_lin + (1 - a) * lin_raw, a * old_ang + (1 - a) * ang_raw
            out[name] = (lin, ang)
        self._vel = out
        self._prev_rel = rel
        return out

    def _state(self, rel, vel) -> np.ndarray:
        t, m = rel["tip"], rel["mid"]
        q = lambda x: x if x[0] >= 0 else -x
        return np.concatenate([t.position, q(t.quaternion), m.position, q(m.quaternion), vel["tip"][0], vel["tip"][1],
                               vel["mid"][0], vel["mid"][1], self.safety.last_command / self.limits.p_max]).astype(np.float32)

    def _read(self):
        try:
            number, poses = self.mocap.latest()
        except Exception as e:  # noqa: BLE001
            self.safety.fault(f"motion capture raised {type(e).__name__}: {e}")
        now = self.clock.now()
        tip_rel = None
        if number >= 0 and all(p.valid for p in poses.values()) and self._base_ref is not None:
            tip_rel = self._relative(poses)["tip"].position
        self.safety.check_frame(number, poses, now, tip_rel)
        return number, poses

    def _td(self, obs, reward=None, done=False, overrun=False, fault=False, truncated=False):
        b = lambda x: torch.tensor([bool(x)])
        td = TensorDict({
            "observation": torch.as_tensor(obs), "overrun": b(overrun), "safety_fault": b(fault),
            "done": b(done or truncated), "terminated": b(done), "truncated": b(truncated)}, [])
        if reward is not None:
            td.set("reward", torch.tensor([float(reward)], dtype=torch.float32))
        return td

    # ------------------------------------------------------------------ EnvBase API
    def _set_seed(self, seed):
        self._rng = np.random.default_rng(seed)
        if self.twin is not None:
            self.twin.rng = np.random.default_rng(None if seed is None else seed + 1)

    def _reset(self, tensordict=None, **kwargs):
        self.safety.vent("episode reset")
        self._base_ref, self._prev_rel, self._vel, self._steps = None, {}, {}, 0
        if self.twin is not None:
            self.twin.reset_world()
        else:  # hardware: wait until the vented arm settles
            t0 = self.clock.now()
            calm, prev = 0, None
            while calm < 3:
                self.clock.sleep_until(self.clock.now() + self.control_period)
                _, poses = self.mocap.latest()
                tip = poses.get("tip")
                if tip is not None and tip.valid and prev is not None and tip.timestamp > prev.timestamp:
                    speed = np.linalg.norm(tip.position - prev.position) / (tip.timestamp - prev.timestamp)
                    calm = calm + 1 if speed < self.settle_speed else 0
                prev = tip
                if self.clock.now() - t0 > self.settle_timeout:
                    raise TimeoutError(f"SoPrA did not settle below {self.settle_speed} m/s within {self.settle_timeout} s")
        self.safety.rearm()  # vented and settled: commands are accepted again
        if self.task == "reach-random" and self._fixed_target is None:
            self.target = self.sample_target()
        # wait (up to ~one control period x stale factor) for a complete frame to re-zero on
        deadline = self.clock.now() + self.limits.stale_factor * self.control_period
        while True:
            number, poses = self.mocap.latest()
            if number >= 0 and poses and all(p.valid for p in poses.values()):
                break
            if self.clock.now() > deadline:
                self.safety.fault("no complete motion-capture frame at reset")
            self.clock.sleep_until(self.clock.now() + self.control_period / 10)
        self.safety.check_frame(number, poses, self.clock.now())
        self._base_ref = poses["base"]  # re-zero on the base ring
        rel = self._relative(poses)
        obs = self._state(rel, self._velocities(rel))
        self._last_obs = obs
        self._tick = self.clock.now()
        self._last_wall = time.perf_counter()
        return self._td(obs)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        from torchrl_softae.envs.robots.checks import check_action

        wall = time.perf_counter()
        overrun = self._last_wall is not None and wall - self._last_wall > self.control_period
        self.timing["periods"].append(wall - self._last_wall if self._last_wall is not None else float("nan"))
        self.timing["overruns"] += int(overrun)
        self.timing["steps"] += 1
        self._steps += 1
        fault = False
        try:
            try:
                action = check_action("SoPrAEnv", tensordict.get("action").detach().cpu().numpy(), N_CHAMBERS)
            except ValueError as e:  # a controller that emits garbage is a fault, not a crash mid-episode
                self.safety.fault(str(e))
            self.safety.command(self.safety.last_command + self.max_step * action)
            self._tick += self.control_period
            self.clock.sleep_until(self._tick)
            number, poses = self._read()
            rel = self._relative(poses)
            obs = self._state(rel, self._velocities(rel))
        except SafetyFault:
            fault, obs = True, self._last_obs
        if self.safety.latched is not None:  # the watchdog tripped meanwhile: this step reports it
            fault = True
        self._last_obs = obs
        reward = 0.0
        if self.task is not None and not fault:
            from torchrl_softae.envs.robots.reach import reach_reward

            reward = float(reach_reward(np.linalg.norm(obs[0:3] - self.target)))
        truncated = self._steps >= self.max_steps
        if fault or truncated:
            self.safety.end_episode()  # vented before control returns: retraining never runs pressurized
        self._last_wall = time.perf_counter()
        return self._td(obs, reward, done=fault, overrun=overrun, fault=fault, truncated=truncated)

    def sample_target(self) -> np.ndarray:
        """A reachable target: the twin's settled tip under random pressures within the cap."""
        from torchrl_softae.envs.robots.sopra.sim import SoPrASim

        twin = SoPrASim(self.twin.p if self.twin is not None else None, seed=int(self._rng.integers(1 << 30)))
        p = self._rng.uniform(0, self.limits.p_max, N_CHAMBERS) * (self._rng.random(N_CHAMBERS) < 0.5)
        twin.send_pressures(p)
        twin.sleep_until(2.0)
        return twin._true_poses()["tip"].position.copy()

    def close(self, *args, **kwargs):
        self.safety.close()
        try:
            self.mocap.close()
        finally:
            super().close(*args, **kwargs)


class SoPrAGymEnv:
    """gymnasium view of :class:`SoPrAEnv` on the simulated twin (registered as ``SoPrA-v0``)."""

    def __new__(cls, **kwargs):
        import gymnasium as gym
        from gymnasium import spaces

        class _SoPrAGym(gym.Env):
            metadata = {"render_modes": []}

            def __init__(self, task=None, max_steps=200, **kw):
                self.env = SoPrAEnv("sim", task=task, max_steps=max_steps, install_signal_handlers=False, **kw)
                self.observation_space = spaces.Box(-np.inf, np.inf, (32,), dtype=np.float32)
                self.action_space = spaces.Box(-1.0, 1.0, (N_CHAMBERS,), dtype=np.float32)

            def reset(self, *, seed=None, options=None):
                super().reset(seed=seed)
                if seed is not None:
                    self.env.set_seed(seed)
                td = self.env.reset()
                return td["observation"].numpy(), {"target": self.env.target.copy()}

            def step(self, action):
                td = self.env.step(TensorDict({"action": torch.as_tensor(np.asarray(action), dtype=torch.float32)}, []))
                nxt = td["next"]
                info = {"overrun": bool(nxt["overrun"]), "safety_fault": bool(nxt["safety_fault"]),
                        "pressures": self.env.safety.last_command.copy()}
                return (nxt["observation"].numpy(), float(nxt["reward"]), bool(nxt["terminated"]),
                        bool(nxt["truncated"]), info)

            def close(self):
                self.env.close()

        return _SoPrAGym(**kwargs)
