"""Musculoskeletal leg driven by electrohydraulic (Peano-HASEL) muscles on a boom (paper:
"Musculoskeletal Leg with Electrohydraulic Muscles"; Table S3 state layout, Table S5 rewards).

A MuJoCo proxy of the lab's leg (Buchner et al. 2024), whose model and learned muscle network are
not public. A planar two-joint leg (hip, knee, round foot with ground contact) hangs at the end of
a 1 m boom that turns around a vertical post, so the leg hops along a circular track. Boom joints:
yaw (around the post, passive), pitch (up/down, passive), roll (about the boom's axis, driven by a
position-controlled DC motor: tilting the leg sets the hopping direction). Four muscles in two
antagonistic pairs (hip flexor/extensor, knee flexor/extensor) are spatial tendons whose pulling
force comes from :class:`HaselMuscleModel`.

Timing: MuJoCo step 0.5 ms (implicitfast), 20 substeps per 10 ms control step (500 steps = 5 s).

Observation (Table S3): boom yaw 0, pitch 1, roll 2, hip 3, knee 4, then the five angular
velocities 5:10. Action (5): DC-motor roll target (index 0, [-1, 1] -> +-0.35 rad) and four
muscle voltages (1:5, [-1, 1] -> [0, 8 kV]: hip flexor, hip extensor, knee flexor, knee extensor).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from gymnasium import spaces

from torchrl_softae.envs.robots.mujoco_base import MujocoRobotEnv, check_action

__all__ = ["HaselMuscleModel", "MSKLegEnv", "LEG_XML", "leg_layout", "MUSCLES"]

MUSCLES = ("hip_flexor", "hip_extensor", "knee_flexor", "knee_extensor")


@dataclass
class HaselMuscleModel:
    """Quasi-static Peano-HASEL force model with a first-order electrical lag.

    Force (contraction only) ``F = F_max * (V / V_max)^2 * max(0, 1 - strain / strain_max)``, where
    ``strain = (L_rest - L) / L_rest`` is the contraction of the muscle; the electrostatic zipping
    force grows with the square of the voltage and vanishes when the pouches are fully zipped at
    the maximum strain (Kellaris et al. 2018, Sci. Robot.; Kellaris et al. 2019, Adv. Sci.).
    The voltage follows the command through the RC charging of the electrodes, ``dV/dt = (V_cmd -
    V) / tau``. Defaults: 8 kV, 40 N per muscle (a stack of pouches), 15 % strain, tau = 5 ms --
    the order of magnitude of the actuators in Buchner et al. 2024, which hop above 5 Hz.

    Replace this class (same :meth:`force` signature) by a learned or measured force model.
    """

    v_max: float = 8000.0
    f_max: float = 40.0
    strain_max: float = 0.15
    tau: float = 0.005

    def voltage_step(self, v: np.ndarray, v_cmd: np.ndarray, dt: float) -> np.ndarray:
        return v + (v_cmd - v) * (1.0 - np.exp(-dt / self.tau))

    def force(self, voltage: np.ndarray, length: np.ndarray, rest_length: np.ndarray) -> np.ndarray:
        strain = (rest_length - length) / rest_length
        active = np.clip(1.0 - strain / self.strain_max, 0.0, 1.0)
        return self.f_max * np.square(np.clip(voltage / self.v_max, 0.0, 1.0)) * active


def _leg_xml() -> str:
    return """
<mujoco model="msk_leg">
  <compiler angle="radian"/>
  <option timestep="0.0005" integrator="implicitfast" gravity="0 0 -9.81"/>
  <default>
    <geom contype="0" conaffinity="0" rgba="0.7 0.7 0.75 1"/>
    <site size="0.004" rgba="0.9 0.2 0.2 1"/>
  </default>
  <worldbody>
    <light pos="0 0 3" dir="0 0 -1"/>
    <geom name="floor" type="plane" size="3 3 0.1" contype="1" conaffinity="1" friction="1.0 0.005 0.0001" rgba="0.3 0.35 0.3 1"/>
    <geom name="post" type="cylinder" fromto="0 0 0 0 0 0.42" size="0.02"/>
    <body name="boom" pos="0 0 0.40">
      <joint name="yaw" type="hinge" axis="0 0 1" damping="0.02"/>
      <joint name="pitch" type="hinge" axis="0 -1 0" damping="0.02" range="-0.6 0.6" limited="true"/>
      <joint name="roll" type="hinge" axis="1 0 0" damping="0.05" range="-0.6 0.6" limited="true"/>
      <geom type="capsule" fromto="0 0 0 1.0 0 0" size="0.008" mass="0.08"/>
      <geom type="sphere" pos="-0.25 0 0" size="0.03" mass="0.25"/>
      <body name="hip" pos="1.0 0 0">
        <geom type="box" size="0.025 0.03 0.02" mass="0.12"/>
        <site name="hip_front" pos="0 0.035 -0.01"/>
        <site name="hip_back" pos="0 -0.035 -0.01"/>
        <body name="thigh" pos="0 0 -0.02">
          <joint name="hip" type="hinge" axis="1 0 0" range="-1.0 1.0" limited="true" damping="0.005" stiffness="0.2"/>
          <geom type="capsule" fromto="0 0 0 0 0 -0.16" size="0.01" mass="0.04"/>
          <site name="thigh_front_top" pos="0 0.018 -0.05"/>
          <site name="thigh_back_top" pos="0 -0.018 -0.05"/>
          <site name="thigh_front_low" pos="0 0.018 -0.12"/>
          <site name="thigh_back_low" pos="0 -0.018 -0.12"/>
          <body name="shank" pos="0 0 -0.16">
            <joint name="knee" type="hinge" axis="1 0 0" range="-0.1 1.8" limited="true" damping="0.005" stiffness="0.3" springref="0.5"/>
            <geom type="capsule" fromto="0 0 0 0 0 -0.16" size="0.008" mass="0.03"/>
            <site name="shank_front" pos="0 0.018 -0.04"/>
            <site name="shank_back" pos="0 -0.018 -0.04"/>
            <geom name="foot" type="sphere" pos="0 0 -0.16" size="0.015" mass="0.01" contype="1" conaffinity="1" friction="1.2 0.005 0.0001"/>
          </body>
        </body>
      </body>
    </body>
  </worldbody>
  <tendon>
    <spatial name="hip_flexor"><site site="hip_front"/><site site="thigh_front_top"/></spatial>
    <spatial name="hip_extensor"><site site="hip_back"/><site site="thigh_back_top"/></spatial>
    <spatial name="knee_flexor"><site site="thigh_front_low"/><site site="shank_front"/></spatial>
    <spatial name="knee_extensor"><site site="thigh_back_low"/><site site="shank_back"/></spatial>
  </tendon>
  <actuator>
    <position name="roll_motor" joint="roll" kp="8" kv="0.3" ctrlrange="-0.35 0.35" ctrllimited="true" forcerange="-2 2" forcelimited="true"/>
    <motor name="hip_flexor" tendon="hip_flexor" gear="1" ctrlrange="-200 0" ctrllimited="true"/>
    <motor name="hip_extensor" tendon="hip_extensor" gear="1" ctrlrange="-200 0" ctrllimited="true"/>
    <motor name="knee_flexor" tendon="knee_flexor" gear="1" ctrlrange="-200 0" ctrllimited="true"/>
    <motor name="knee_extensor" tendon="knee_extensor" gear="1" ctrlrange="-200 0" ctrllimited="true"/>
  </actuator>
</mujoco>"""


LEG_XML = _leg_xml()


def leg_layout() -> dict[str, int | slice]:
    return {"yaw": 0, "pitch": 1, "roll": 2, "hip": 3, "knee": 4, "boom_velocities": slice(5, 8),
            "joint_velocities": slice(8, 10)}


class MSKLegEnv(MujocoRobotEnv):
    """Hopping leg on a boom with HASEL muscles (``MSKLeg-v0``).

    Args:
        task (str, optional): ``"ccw"`` (vii, reward +yaw rate) or ``"cw"`` (viii, -yaw rate);
            ``None`` gives reward 0.
        muscle_model: a :class:`HaselMuscleModel` (or anything with ``voltage_step``/``force``).
        max_episode_steps (int): default 500.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 100}
    frame_skip = 20
    roll_range = 0.35

    def __init__(self, task: str | None = None, muscle_model: HaselMuscleModel | None = None,
                 max_episode_steps: int = 500, render_mode: str | None = None):
        import mujoco

        if task not in (None, "ccw", "cw"):
            raise ValueError(f"MSKLegEnv: task={task!r}; valid: ccw, cw, None")
        self.task = task
        self.muscles = muscle_model or HaselMuscleModel()
        self.max_episode_steps = max_episode_steps
        self.render_mode = render_mode
        self._mj = mujoco
        self.model = mujoco.MjModel.from_xml_string(LEG_XML)
        self.data = mujoco.MjData(self.model)
        self.observation_space = spaces.Box(-np.inf, np.inf, (10,), dtype=np.float32)
        self.action_space = spaces.Box(-1.0, 1.0, (5,), dtype=np.float32)
        names = ("yaw", "pitch", "roll", "hip", "knee")
        self._qpos = np.array([self.model.joint(n).qposadr[0] for n in names])
        self._qvel = np.array([self.model.joint(n).dofadr[0] for n in names])
        self._tendons = np.array([self.model.tendon(n).id for n in MUSCLES])
        mujoco.mj_forward(self.model, self.data)
        self._rest_length = self.data.ten_length[self._tendons].copy()
        self._voltage = np.zeros(4)
        self._steps = 0

    def _obs(self) -> np.ndarray:
        return np.concatenate([self.data.qpos[self._qpos], self.data.qvel[self._qvel]]).astype(np.float32)

    @property
    def muscle_forces(self) -> np.ndarray:
        return self.muscles.force(self._voltage, self.data.ten_length[self._tendons], self._rest_length)

    def foot_height(self) -> float:
        return float(self.data.geom("foot").xpos[2] - self.model.geom("foot").size[0])

    def _info(self, diverged=False) -> dict:
        return {"yaw": float(self.data.qpos[self._qpos[0]]),
                "foot_height": np.array([self.foot_height()], dtype=np.float32),
                "muscle_forces": self.muscle_forces, "voltages": self._voltage.copy(), "diverged": diverged}

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self._mj.mj_resetData(self.model, self.data)
        self.data.qpos[self._qpos[0]] = self.np_random.uniform(-0.05, 0.05)  # yaw
        self.data.qpos[self._qpos[4]] = 0.5 + self.np_random.uniform(-0.05, 0.05)  # knee at its spring rest
        self._voltage[:] = 0.0
        self._mj.mj_forward(self.model, self.data)
        for _ in range(1000):  # settle on the ground (0.5 s, unactuated)
            self._mj.mj_step(self.model, self.data)
        self._steps = 0
        return self._obs(), self._info()

    def step(self, action):
        a = check_action("MSKLegEnv", action, 5)
        self.data.ctrl[0] = self.roll_range * a[0]
        v_cmd = (a[1:] + 1.0) / 2.0 * self.muscles.v_max
        dt = self.model.opt.timestep
        yaw0 = float(self.data.qpos[self._qpos[0]])

        def muscles():  # RC charging and force of every muscle, each physics substep
            self._voltage = self.muscles.voltage_step(self._voltage, v_cmd, dt)
            self.data.ctrl[1:5] = -self.muscle_forces  # tendon actuators pull (negative = shortening)

        unstable = self._simulate(self.frame_skip, muscles)
        obs = self._obs()
        diverged = bool(unstable or not np.all(np.isfinite(obs)) or np.abs(obs[5:]).max() > 500)
        self._steps += 1
        reward = 0.0
        if self.task is not None and not diverged:
            yaw_rate = (float(self.data.qpos[self._qpos[0]]) - yaw0) / (self.frame_skip * dt)
            reward = yaw_rate if self.task == "ccw" else -yaw_rate
        return obs, reward, diverged, self._steps >= self.max_episode_steps, self._info(diverged)

    def render(self):
        return self._render_from(self.data.body("hip").xpos, 0.9, -15.0, 0.0)
