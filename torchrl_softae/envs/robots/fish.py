"""Articulated fish swimming in a viscous fluid, on MuJoCo's fluid model (paper: "Articulated Fish
with Deformable Skin in Fluid"; Table S2 state layout, Table S5 rewards).

A proxy for FishGym (which needs CUDA and is no longer published): a planar chain of ellipsoids --
head, four body segments and a caudal fin -- neutrally buoyant in water (density 1000 kg/m^3,
viscosity 1e-3 Pa s) with MuJoCo's ellipsoid fluid model (added mass, viscous and quadratic drag,
Kutta lift), integrated with implicitfast at 2 ms, 10 substeps per 20 ms control step. Joints
1-4 are torque-actuated (action [-1, 1]^4 times 0.4 N m); joint 5, the fin, is passive with a
spring-damper standing in for the compliant skin. The root moves in the horizontal plane only
(slide x, slide y, hinge yaw): no buoyancy control, as in the paper.

Observation (Table S2; all in the world frame, angles unwrapped):
15D: base linear velocity (vx, vy, vz = 0) 0:3, head yaw 3, head yaw rate 4, joint positions
5:10, joint velocities 10:15. 18D prepends the target position relative to the head (3).
"""
from __future__ import annotations

import math

import numpy as np
from gymnasium import spaces

from torchrl_softae.envs.robots.mujoco_base import MujocoRobotEnv, check_action

__all__ = ["SoftFishEnv", "FISH_XML", "fish_layout"]

SEGMENTS = [  # (name, half-length, half-width, half-height) of the ellipsoids, head first
    ("head", 0.060, 0.028, 0.035),
    ("seg1", 0.045, 0.026, 0.032),
    ("seg2", 0.040, 0.022, 0.028),
    ("seg3", 0.035, 0.016, 0.022),
    ("seg4", 0.030, 0.010, 0.016),
    ("fin", 0.030, 0.003, 0.045),  # thin, tall caudal fin: most of the thrust
]


def _fish_xml() -> str:
    body_xml = ""
    close = ""
    x = 0.0
    for i, (name, hl, hw, hh) in enumerate(SEGMENTS):
        if i == 0:
            body_xml += (
                f'<body name="{name}" pos="0 0 0">'
                '<joint name="root_x" type="slide" axis="1 0 0" damping="0"/>'
                '<joint name="root_y" type="slide" axis="0 1 0" damping="0"/>'
                '<joint name="root_yaw" type="hinge" axis="0 0 1" damping="0"/>'
                f'<geom type="ellipsoid" size="{hl} {hw} {hh}" pos="0 0 0" fluidshape="ellipsoid" density="1000"/>'
                '<site name="head_site" pos="0 0 0"/>'
            )
            x = -hl
        else:
            if i < len(SEGMENTS) - 1:
                joint = f'<joint name="j{i}" type="hinge" axis="0 0 1" range="-60 60" limited="true" damping="0.002"/>'
            else:  # passive compliant fin
                joint = f'<joint name="j{i}" type="hinge" axis="0 0 1" range="-60 60" limited="true" stiffness="0.05" damping="0.002"/>'
            body_xml += (
                f'<body name="{name}" pos="{x:.4f} 0 0">{joint}'
                f'<geom type="ellipsoid" size="{hl} {hw} {hh}" pos="{-hl:.4f} 0 0" fluidshape="ellipsoid" density="1000"/>'
            )
            x = -2 * hl
        close += "</body>"
    motors = "".join(f'<motor name="m{i}" joint="j{i}" gear="0.4" ctrlrange="-1 1" ctrllimited="true"/>' for i in range(1, 5))
    return f"""
<mujoco model="soft_fish">
  <option timestep="0.002" integrator="implicitfast" density="1000" viscosity="0.001" gravity="0 0 0"/>
  <default><geom contype="0" conaffinity="0" rgba="0.9 0.5 0.2 1"/></default>
  <worldbody>
    <light pos="0 0 3" dir="0 0 -1"/>
    <geom name="floor" type="plane" size="5 5 0.1" pos="0 0 -0.3" rgba="0.2 0.3 0.5 1"/>
    {body_xml}{close}
    <body name="target" mocap="true" pos="1 0 0"><geom type="sphere" size="0.03" rgba="0.2 0.9 0.2 0.8"/></body>
  </worldbody>
  <actuator>{motors}</actuator>
</mujoco>"""


FISH_XML = _fish_xml()


def fish_layout(with_target: bool) -> dict[str, slice]:
    o = 3 if with_target else 0
    lay = {"velocity": slice(o, o + 3), "yaw": slice(o + 3, o + 4), "yaw_rate": slice(o + 4, o + 5),
           "joint_positions": slice(o + 5, o + 10), "joint_velocities": slice(o + 10, o + 15)}
    if with_target:
        lay = {"target": slice(0, 3), **lay}
    return lay


class SoftFishEnv(MujocoRobotEnv):
    """Planar articulated fish in MuJoCo's fluid.

    Args:
        with_target (bool): 18D observation with the target position relative to the head
            (``SoftFishTarget-v0``); the target is drawn at reset, 0.5-1.5 m away in any direction.
        task (str, optional): ``"forward"`` (iii, reward v_x), ``"backward"`` (iv, -v_x; the fish
            starts heading +x, so it must turn), ``"to-target"`` (v, -||p - p_target||),
            ``"from-target"`` (vi, +||p - p_target||), or ``None`` (reward 0).
        max_episode_steps (int): default 200.

    ``info``: ``position`` (head x, y), ``yaw``, ``diverged``.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 50}
    frame_skip = 10
    TASKS = ("forward", "backward", "to-target", "from-target")

    def __init__(self, with_target: bool = False, task: str | None = None, max_episode_steps: int = 200,
                 render_mode: str | None = None):
        import mujoco

        if task is not None and task not in self.TASKS:
            raise ValueError(f"SoftFishEnv: task={task!r}; valid: {', '.join(self.TASKS)}, None")
        if task in ("to-target", "from-target") and not with_target:
            raise ValueError(f"SoftFishEnv: task {task!r} needs with_target=True (SoftFishTarget-v0)")
        self.with_target, self.task = with_target, task
        self.max_episode_steps = max_episode_steps
        self.render_mode = render_mode
        self.model = mujoco.MjModel.from_xml_string(FISH_XML)
        self.data = mujoco.MjData(self.model)
        self._mj = mujoco
        d = 18 if with_target else 15
        self.observation_space = spaces.Box(-np.inf, np.inf, (d,), dtype=np.float32)
        self.action_space = spaces.Box(-1.0, 1.0, (4,), dtype=np.float32)
        self._qpos_joints = [self.model.joint(f"j{i}").qposadr[0] for i in range(1, 6)]
        self._qvel_joints = [self.model.joint(f"j{i}").dofadr[0] for i in range(1, 6)]
        self.target = np.array([1.0, 0.0, 0.0])
        self._steps = 0

    @property
    def position(self) -> np.ndarray:
        return self.data.qpos[:2].copy()

    @property
    def yaw(self) -> float:
        return float(self.data.qpos[2])

    def _obs(self) -> np.ndarray:
        qv = self.data.qvel
        vel = np.array([qv[0], qv[1], 0.0])
        parts = [vel, [self.data.qpos[2]], [qv[2]], self.data.qpos[self._qpos_joints], qv[self._qvel_joints]]
        if self.with_target:
            rel = self.target - np.array([*self.data.qpos[:2], 0.0])
            parts.insert(0, rel)
        return np.concatenate(parts).astype(np.float32)

    def _info(self, diverged=False) -> dict:
        return {"position": self.position.astype(np.float32), "yaw": self.yaw, "target": self.target.copy(),
                "diverged": diverged}

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self._mj.mj_resetData(self.model, self.data)
        # small random initial joint angles so episodes differ, heading +x
        self.data.qpos[self._qpos_joints] = self.np_random.uniform(-0.05, 0.05, 5)
        if self.with_target:
            r, phi = self.np_random.uniform(0.5, 1.5), self.np_random.uniform(-math.pi, math.pi)
            self.target = np.array([r * math.cos(phi), r * math.sin(phi), 0.0])
            self.data.mocap_pos[0] = self.target
        self._mj.mj_forward(self.model, self.data)
        self._steps = 0
        return self._obs(), self._info()

    def step(self, action):
        self.data.ctrl[:] = check_action("SoftFishEnv", action, 4)
        p0 = self.position
        unstable = self._simulate(self.frame_skip)
        obs = self._obs()
        diverged = bool(unstable or not np.all(np.isfinite(obs)) or np.abs(self.data.qvel).max() > 1e3)
        self._steps += 1
        reward = 0.0
        if not diverged and self.task is not None:
            vx = (self.position[0] - p0[0]) / (self.frame_skip * self.model.opt.timestep)
            dist = float(np.linalg.norm(self.target[:2] - self.position))
            reward = {"forward": vx, "backward": -vx, "to-target": -dist, "from-target": dist}[self.task]
        return obs, float(reward), diverged, self._steps >= self.max_episode_steps, self._info(diverged)

    def render(self):
        return self._render_from([*self.position, 0.0], 1.2, -89.0, 90.0)
