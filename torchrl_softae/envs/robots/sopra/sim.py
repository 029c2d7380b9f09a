"""SoPrA's simulated twin: the ``sim`` backend, speaking the same protocols as the hardware.

Arm: two 0.125 m segments (Toshimitsu et al. 2021, "SoPrA: fabrication & dynamical modeling of a
scalable soft continuum robotic arm with integrated proprioceptive sensing") as one PyElastica
Cosserat rod hanging down under gravity: radius 20 mm, density 1080 kg/m^3 (silicone), E = 0.15
MPa (DragonSkin 10 range), 16 elements, damping 3 /s. Each segment has three chambers at 120
degrees, 12 mm off the axis with a 6 mm bore; a chamber at pressure p adds the bending moment
``p * pi * 6mm^2 * 12mm`` over its segment (about 60 degrees of segment bending at 1200 mbar).
Valves: first-order lag (50 ms) after a 20 ms transport delay. Motion capture: 100 Hz, 5 ms
latency, 0.2 mm / 0.2 degree noise, each body lost on 0.05 % of frames. Time is simulated:
``sleep_until`` advances the physics, so the twin runs faster than real time.
"""
from __future__ import annotations

import collections
import math
from dataclasses import dataclass

import numpy as np

from torchrl_softae.envs.robots.rotations import quat_mul, rotation_to_quaternion
from torchrl_softae.envs.robots.sopra.backends import N_CHAMBERS, Pose

__all__ = ["SoPrATwinParameters", "SoPrASim"]


@dataclass
class SoPrATwinParameters:
    segment_length: float = 0.125
    radius: float = 0.02
    density: float = 1080.0
    youngs_modulus: float = 1.5e5
    n_elements: int = 16
    damping: float = 3.0
    dt: float = 2e-4
    chamber_offset: float = 0.012
    chamber_radius: float = 0.006
    valve_tau: float = 0.05
    valve_delay: float = 0.02
    mocap_rate: float = 100.0
    mocap_latency: float = 0.005
    mocap_position_noise: float = 2e-4
    mocap_angle_noise: float = math.radians(0.2)
    mocap_dropout: float = 0.0005


class SoPrASim:
    """Twin of the arm + valves + motion capture, with a simulated clock (``now``/``sleep_until``)."""

    bodies = ("base", "mid", "tip")

    def __init__(self, params: SoPrATwinParameters | None = None, seed: int = 0):
        from torchrl_softae.envs.robots.cosserat import CosseratRodSim, RodParameters

        self.p = p = params or SoPrATwinParameters()
        self.rod = CosseratRodSim(RodParameters(
            length=2 * p.segment_length, radius=p.radius, density=p.density, youngs_modulus=p.youngs_modulus,
            poisson_ratio=0.5, n_elements=p.n_elements, direction=(0.0, 0.0, -1.0), normal=(1.0, 0.0, 0.0),
            damping=p.damping, filter_order=4, gravity=True, dt=p.dt,
        ))
        self.rng = np.random.default_rng(seed)
        # ring frames coincide with the lab frame when the arm hangs straight (base ring = lab)
        self._ring_offset = self.rod.element_rotations([0])[0].T
        angles = 2 * np.pi * np.arange(3) / 3
        # bending couple per unit pressure of each chamber, in the local (d1, d2) plane
        area = np.pi * p.chamber_radius**2
        self._unit_couple = np.stack([np.sin(angles), -np.cos(angles)], 1) * area * p.chamber_offset * 100.0  # per mbar
        self._seg_of_interface = (np.arange(p.n_elements - 1) + 1) >= p.n_elements // 2
        self.connected = True
        self._reset_state()

    def _reset_state(self) -> None:
        self.rod.restore()
        self.time = 0.0
        self.pressure = np.zeros(N_CHAMBERS)  # measured chamber pressures [mbar]
        self._commands = collections.deque([(-1.0, np.zeros(N_CHAMBERS))])
        self._frame_number = -1
        self._frames = collections.deque()  # (available_at, frame_number, poses)
        self._next_frame_time = 1.0 / self.p.mocap_rate
        self._capture()
        self._published = self._frames.popleft()[1:]

    def reset_world(self) -> None:
        """Put the twin back to a straight, vented arm at t = 0 (no real-robot counterpart)."""
        self._reset_state()

    # ------------------------------------------------------------------ clock
    def now(self) -> float:
        return self.time

    def sleep_until(self, t: float) -> None:
        tick = 1.0 / self.p.mocap_rate
        while self.time < t - 1e-9:
            self._advance(min(t, self._next_frame_time) - self.time)
            if self.time >= self._next_frame_time - 1e-9:
                self._capture()
                self._next_frame_time += tick
            self._publish()

    def _advance(self, duration: float) -> None:
        p = self.p
        steps = max(1, int(round(duration / p.dt)))
        for _ in range(steps):
            # valves: command applied after the transport delay, then first-order tracking
            while len(self._commands) > 1 and self._commands[1][0] <= self.time - p.valve_delay:
                self._commands.popleft()
            target = self._commands[0][1]
            self.pressure += (target - self.pressure) * (1 - math.exp(-p.dt / p.valve_tau))
            self._apply_pressures()
            self.rod.advance(p.dt)
            self.time += p.dt

    def _apply_pressures(self) -> None:
        m1 = self.pressure[:3] @ self._unit_couple  # segment 1 (base side), (2,)
        m2 = self.pressure[3:] @ self._unit_couple
        self.rod.target_couples[:2] = np.where(self._seg_of_interface, m2[:, None], m1[:, None])

    # ------------------------------------------------------------------ motion capture
    def _true_poses(self) -> dict[str, Pose]:
        n = self.p.n_elements
        nodes = self.rod.node_positions()
        R = self.rod.element_rotations([0, n // 2 - 1, n - 1])
        return {name: Pose(nodes[i].copy(), rotation_to_quaternion(R[k] @ self._ring_offset), self.time)
                for k, (name, i) in enumerate(zip(self.bodies, (0, n // 2, n)))}

    def _capture(self) -> None:
        p = self.p
        self._frame_number += 1
        poses = {}
        for name, pose in self._true_poses().items():
            if self.rng.random() < p.mocap_dropout:
                poses[name] = Pose(np.full(3, np.nan), np.full(4, np.nan), self.time)
                continue
            pos = pose.position + self.rng.normal(0, p.mocap_position_noise, 3)
            axis = self.rng.normal(size=3)
            half = 0.5 * self.rng.normal(0, p.mocap_angle_noise)
            dq = np.r_[math.cos(half), math.sin(half) * axis / np.linalg.norm(axis)]
            q = quat_mul(pose.quaternion, dq)
            poses[name] = Pose(pos, q if q[0] >= 0 else -q, self.time)
        self._frames.append((self.time + p.mocap_latency, self._frame_number, poses))

    def _publish(self) -> None:
        while self._frames and self._frames[0][0] <= self.time + 1e-12:
            _, number, poses = self._frames.popleft()
            self._published = (number, poses)

    # ------------------------------------------------------------------ MotionCapture protocol
    def start(self) -> None:
        pass

    def latest(self):
        return self._published

    # ------------------------------------------------------------------ ValveArray protocol
    def send_pressures(self, mbar) -> None:
        mbar = np.asarray(mbar, dtype=np.float64)
        if mbar.shape != (N_CHAMBERS,) or not np.all(np.isfinite(mbar)) or np.any(mbar < 0):
            raise ValueError(f"SoPrASim: pressures {mbar} must be 6 finite values >= 0 mbar")
        self._commands.append((self.time, mbar.copy()))

    def read_pressures(self) -> np.ndarray:
        return self.pressure.copy()

    def vent(self) -> None:
        self._commands.clear()
        self._commands.append((self.time - self.p.valve_delay, np.zeros(N_CHAMBERS)))

    def close(self) -> None:
        pass
