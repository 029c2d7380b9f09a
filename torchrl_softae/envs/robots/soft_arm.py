"""Soft continuum arm: a clamped Cosserat rod in PyElastica (paper: "Soft Continuum Arm via
Cosserat Rod Simulation"; supplement Table S1 state layout, Table S5 reward).

Physics (after Naughton et al. 2021, 3-D tracking case): a 1 m rod of radius 5 cm, density
1000 kg/m^3, Young's modulus 1 MPa (Poisson 0.5), 20 elements, clamped at the origin and pointing
up (+z), analytical linear damping 5 /s plus a Laplace dissipation filter, PositionVerlet with
dt = 2e-4 s; optional gravity (-z). The actuators build torque with a 50 ms first-order lag.
Actuation: internal couples in the local normal (d1) and binormal (d2) directions whose profile
along the arm is a cubic spline through 6 equidistant control points; action [-1, 1]^12 =
(normal 0:6, binormal 6:12) scaled by ``max_torque`` [N m]. One control step = 100 substeps
= 20 ms, so 200 steps = 4 s, several times the arm's slowest bending period.

Observation (Table S1), with P observed points evenly spaced along the rod (P = 5 -> 58D,
P = 11 -> 136D), all in the base frame: point positions (3P), point linear velocities (3P),
orientations of the P-1 segments between points as unit quaternions (w, x, y, z), w >= 0
(4(P-1)), and their angular velocities in the base frame (3(P-1)).
"""
from __future__ import annotations


import gymnasium as gym
import numpy as np
from gymnasium import spaces

from torchrl_softae.envs.robots.rotations import rotation_to_quaternion
from torchrl_softae.envs.robots.reach import reach_reward

__all__ = ["SoftArmEnv", "reach_reward", "ARM_TARGETS", "ARM_TARGETS_V1", "arm_layout", "step_response"]


def arm_layout(points: int) -> dict[str, slice]:
    """Index ranges of the observation for ``points`` observed points (Table S1)."""
    p, s = 3 * points, points - 1
    return {
        "positions": slice(0, p),
        "velocities": slice(p, 2 * p),
        "orientations": slice(2 * p, 2 * p + 4 * s),
        "angular_velocities": slice(2 * p + 4 * s, 2 * p + 7 * s),
    }


# Targets of tasks (i) and (ii): tip positions the arm reaches at steady state under a constant
# action (so they are reachable by construction), written out for readability and checked in tests.
# (i): binormal 0.3 everywhere (about 17 degrees at the tip); (ii): normal -0.6 and binormal 0.9
# (about 65 degrees, near the workspace edge); both settled for 400 control steps.
ARM_TARGETS = {
    "reach-close": np.array([0.2819, 0.0, 0.9433]),
    "reach-far": np.array([0.5835, 0.3890, 0.4054]),
}
ARM_TARGET_ACTIONS = {
    "reach-close": np.r_[np.zeros(6), 0.3 * np.ones(6)],
    "reach-far": np.r_[-0.6 * np.ones(6), 0.9 * np.ones(6)],
}

# SoftArm-v1 (100 ms control period). (i) is v0's close target (0.29 m from the rest tip). (ii) is
# 0.62 m from the rest tip, 6 cm away from every tip a uniform bending profile can hold (any
# constant curvature in any direction): reaching it needs the base and the tip bent differently
# (normal -0.285 on the lower half, +0.89 on the upper; binormal 0.625 / 0.959). Settled tips of
# these actions after 40 control steps, checked in the tests.
ARM_TARGETS_V1 = {
    "reach-close": np.array([0.2818, 0.0, 0.9434]),
    "reach-far": np.array([0.5305, -0.0473, 0.6849]),
}
ARM_TARGET_ACTIONS_V1 = {
    "reach-close": np.r_[np.zeros(6), 0.3 * np.ones(6)],
    "reach-far": np.r_[np.full(3, -0.285), np.full(3, 0.89), np.full(3, 0.625), np.full(3, 0.959)],
}
TARGET_SETS = {"v0": ARM_TARGETS, "v1": ARM_TARGETS_V1}


def _spline_basis(n_interfaces: int, n_control: int = 6) -> np.ndarray:
    """(n_interfaces, n_control) matrix mapping control-point values to the torque profile:
    the natural cubic spline through ``n_control`` equidistant points on s in [0, 1]."""
    from scipy.interpolate import CubicSpline

    xs = np.linspace(0.0, 1.0, n_control)
    s = np.linspace(0.0, 1.0, n_interfaces + 2)[1:-1]  # interior element interfaces
    return np.stack([CubicSpline(xs, np.eye(n_control)[i], bc_type="natural")(s) for i in range(n_control)], 1)


class SoftArmEnv(gym.Env):
    """Clamped Cosserat-rod arm with 12 spline-profiled bending torques.

    Args:
        observed_points (int): 5 (58D state) or 11 (136D). Default 5.
        task (str, optional): ``"reach-close"`` (i), ``"reach-far"`` (ii), ``"reach-random"``
            (target uniform from the reachable workspace at every reset) or ``None`` (reward 0:
            task-agnostic exploration).
        target (array, optional): explicit target position (overrides ``task``'s).
        max_torque (float): torque at action 1 [N m]. Default 10 (about 100 degrees of bending at full action).
        gravity (bool): add gravity along -z. Default False.
        n_elements (int): internal elements (a multiple of ``observed_points - 1``). Default 20.
        max_episode_steps (int): truncation. Default 200.
        divergence_velocity (float): speed [m/s] above which the rod counts as diverged.
        control_period (float): seconds per step (a multiple of the 0.2 ms integration step).
            Default 0.02 (``SoftArm-v0``); ``SoftArm-v1`` uses 0.1, where a full-torque step
            rises (10-90 %) in 9 control steps and settles (5 %) in 12, so the paper's H = 10
            looks across the arm's response (0.02 s: 45 / 58 steps).
        target_set (str): ``"v0"`` or ``"v1"`` targets of tasks (i) and (ii).

    ``info`` holds ``tip`` (position), ``distance`` to the target, and ``diverged`` (bool).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 50}

    dt = 2e-4
    damping = 5.0  # [1/s]
    filter_order = 4
    activation_tau = 0.05  # [s] torque build-up of the actuators

    def __init__(
        self,
        observed_points: int = 5,
        task: str | None = None,
        target=None,
        max_torque: float = 10.0,
        gravity: bool = False,
        n_elements: int = 20,
        max_episode_steps: int = 200,
        divergence_velocity: float = 50.0,
        render_mode: str | None = None,
        control_period: float = 0.02,
        target_set: str = "v0",
    ):
        substeps = int(round(control_period / self.dt))
        if substeps < 1 or abs(substeps * self.dt - control_period) > 1e-9:
            raise ValueError(f"SoftArmEnv: control_period={control_period!r} s, expected a multiple of dt = {self.dt} s")
        if target_set not in TARGET_SETS:
            raise ValueError(f"SoftArmEnv: target_set={target_set!r}; valid: {', '.join(TARGET_SETS)}")
        self.substeps, self.control_period, self.targets = substeps, control_period, TARGET_SETS[target_set]
        if observed_points < 2 or n_elements % (observed_points - 1):
            raise ValueError(
                f"SoftArmEnv: n_elements={n_elements} must be a multiple of observed_points - 1 = {observed_points - 1}"
            )
        if task not in (None, "reach-close", "reach-far", "reach-random"):
            raise ValueError(f"SoftArmEnv: task={task!r}; valid: reach-close, reach-far, reach-random, None")
        self.observed_points = observed_points
        self.n_elements = n_elements
        self.task = task
        self.max_torque = float(max_torque)
        self.gravity = gravity
        self.max_episode_steps = max_episode_steps
        self.divergence_velocity = divergence_velocity
        self.render_mode = render_mode
        self._fixed_target = None if target is None else np.asarray(target, dtype=np.float64)
        d = 3 * observed_points * 2 + 7 * (observed_points - 1)
        self.observation_space = spaces.Box(-np.inf, np.inf, (d,), dtype=np.float32)
        self.action_space = spaces.Box(-1.0, 1.0, (12,), dtype=np.float32)
        self._basis = _spline_basis(n_elements - 1)
        self._build()
        self.target = self._initial_target()
        self._steps = 0

    # ------------------------------------------------------------------ simulator
    def _build(self) -> None:
        from torchrl_softae.envs.robots.cosserat import CosseratRodSim, RodParameters

        self.length = 1.0
        self._rod_sim = CosseratRodSim(RodParameters(
            length=self.length, radius=0.05, density=1000.0, youngs_modulus=1e6, poisson_ratio=0.5,
            n_elements=self.n_elements, damping=self.damping, filter_order=self.filter_order,
            gravity=self.gravity, dt=self.dt, activation_tau=self.activation_tau,
        ))
        self._rod = self._rod_sim.rod
        self._couples = self._rod_sim.target_couples

    def _restore(self) -> None:
        self._rod_sim.restore()

    def _initial_target(self):
        if self._fixed_target is not None:
            return self._fixed_target.copy()
        if self.task in self.targets:
            return self.targets[self.task].copy()
        return np.array([0.0, 0.0, self.length])  # the rest tip, until reset draws a target

    # ------------------------------------------------------------------ observation
    def _observe(self) -> np.ndarray:
        rod, P = self._rod, self.observed_points
        stride = self.n_elements // (P - 1)
        nodes = np.arange(0, self.n_elements + 1, stride)
        base = rod.position_collection[:, 0]
        pos = (rod.position_collection[:, nodes].T - base).reshape(-1)
        vel = rod.velocity_collection[:, nodes].T.reshape(-1)
        mid = np.arange(P - 1) * stride + stride // 2  # middle element of each segment
        R = np.transpose(rod.director_collection[:, :, mid], (2, 1, 0))  # local -> lab (Q^T)
        quat = rotation_to_quaternion(R).reshape(-1)
        # segment angular velocity: mean of its elements' omega (local frame), rotated to the lab frame
        omega_lab = np.einsum("jin,jn->ni", rod.director_collection, rod.omega_collection)
        omega = omega_lab.reshape(P - 1, stride, 3).mean(1).reshape(-1)
        return np.concatenate([pos, vel, quat, omega]).astype(np.float32)

    @property
    def tip(self) -> np.ndarray:
        return (self._rod.position_collection[:, -1] - self._rod.position_collection[:, 0]).copy()

    def _info(self, diverged=False) -> dict:
        tip = self.tip
        return {"tip": tip, "target": self.target.copy(), "distance": float(np.linalg.norm(tip - self.target)),
                "diverged": diverged}

    # ------------------------------------------------------------------ gym API
    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self._restore()
        self._steps = 0
        if self._fixed_target is None and self.task == "reach-random":
            self.target = sample_reachable_target(self.np_random)
        elif options and "target" in options:
            self.target = np.asarray(options["target"], dtype=np.float64)
        else:
            self.target = self._initial_target()
        return self._observe(), self._info()

    def set_action(self, action) -> None:
        from torchrl_softae.envs.robots.checks import check_action

        a = check_action("SoftArmEnv", action, 12)
        torque = self.max_torque * a
        self._couples[0] = self._basis @ torque[:6]  # normal (d1)
        self._couples[1] = self._basis @ torque[6:]  # binormal (d2)

    def step(self, action):
        self.set_action(action)
        diverged = False
        self._rod_sim.advance(self.substeps * self.dt)
        with np.errstate(all="ignore"):
            obs = self._observe()
        speed = self._rod_sim.max_speed()
        if not np.all(np.isfinite(obs)) or not speed < self.divergence_velocity:
            diverged = True
        self._steps += 1
        info = self._info(diverged)
        reward = 0.0 if self.task is None or diverged else float(reach_reward(info["distance"]))
        truncated = self._steps >= self.max_episode_steps
        return obs, reward, diverged, truncated, info

    def render(self):
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        p = self._rod.position_collection
        fig = plt.figure(figsize=(4, 4), dpi=80)
        ax = fig.add_subplot(projection="3d")
        ax.plot(p[0], p[1], p[2], "-", lw=6, color="tab:orange")
        ax.scatter(*self.target, color="tab:green", s=40)
        ax.set_xlim(-1, 1), ax.set_ylim(-1, 1), ax.set_zlim(-0.2, 1.1)
        ax.set_xlabel("x"), ax.set_ylabel("y"), ax.set_zlabel("z")
        fig.canvas.draw()
        frame = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
        plt.close(fig)
        return frame

    def close(self):
        pass


def settle_tip(env: SoftArmEnv, action, steps: int = 200) -> np.ndarray:
    """Tip position after holding ``action`` from rest for ``steps`` control steps."""
    env.reset()
    for _ in range(steps):
        env.step(action)
    return env.tip


_TARGET_ENV = None


def sample_reachable_target(rng: np.random.Generator) -> np.ndarray:
    """A target uniform over reachable tips: settle the arm under a uniform random constant action."""
    global _TARGET_ENV
    if _TARGET_ENV is None:
        _TARGET_ENV = SoftArmEnv()
    return settle_tip(_TARGET_ENV, rng.uniform(-1, 1, 12))


def step_response(env: SoftArmEnv, action, steps: int = 60) -> dict:
    """Tip displacement from rest under a held ``action``: final move [m], 10-90 % rise and 5 %
    settling time in control steps, overshoot (fraction of the final move)."""
    env.reset()
    tips = [env.tip]
    for _ in range(steps):
        env.step(action)
        tips.append(env.tip)
    d = np.linalg.norm(np.array(tips) - tips[0], axis=1)
    final = d[-1]
    outside = np.nonzero(np.abs(d - final) > 0.05 * final)[0]
    return {"final_m": float(final), "rise_steps": int(np.argmax(d >= 0.9 * final) - np.argmax(d >= 0.1 * final)),
            "settle_steps": int(outside[-1] + 1 if len(outside) else 0), "overshoot": float(d.max() / final - 1)}


class RampController:
    """Scripted reaching without any learned model or explored data: the actuation ramps from its
    current value toward a constant action ``a*`` whose settled tip is the target,
    ``a <- a + rate * (a* - a)`` (a first-order command filter, as a valve or motor driver would).
    """

    def __init__(self, goal_action, rate: float = 0.08):
        self.goal = np.asarray(goal_action, dtype=np.float64)
        self.rate = rate
        self.action = np.zeros(12)

    def __call__(self) -> np.ndarray:
        self.action = self.action + self.rate * (self.goal - self.action)
        return self.action.astype(np.float32)


def heldout_transitions(n_targets: int, seed: int, observed_points: int = 5, max_steps: int = 150,
                        tolerance: float = 0.005, progress: bool = False) -> dict:
    """Rollouts of :class:`RampController` toward ``n_targets`` reachable targets (settled tips of
    uniform random constant actions), each trimmed once the tip is within ``tolerance`` (5 mm).

    Returns numpy arrays ``observation``, ``action`` (in [-1, 1]^12), ``next_observation``.
    """
    rng = np.random.default_rng(seed)
    env = SoftArmEnv(observed_points=observed_points, max_episode_steps=max_steps)
    obs_l, act_l, nxt_l = [], [], []
    it = range(n_targets)
    if progress:
        from tqdm.auto import tqdm

        it = tqdm(it, desc="held-out arm rollouts", unit="target")
    for _ in it:
        goal = rng.uniform(-1, 1, 12)
        _reach(env, goal, settle_tip(env, goal), rng.uniform(0.04, 0.2), max_steps, tolerance, (obs_l, act_l, nxt_l))
    return {"observation": np.array(obs_l), "action": np.array(act_l), "next_observation": np.array(nxt_l)}


def _reach(env: SoftArmEnv, goal, target, rate: float, max_steps: int, tolerance: float, out: tuple) -> None:
    """One :class:`RampController` rollout from rest toward ``target`` (the settled tip of
    ``goal``), its transitions appended to the lists ``out``, trimmed once within ``tolerance``."""
    obs_l, act_l, nxt_l = out
    obs, info = env.reset(options={"target": target})
    ctrl = RampController(goal, rate=rate)
    for _ in range(max_steps):
        a = ctrl()
        nxt, _, term, _, info = env.step(a)
        if term:
            break
        obs_l.append(obs), act_l.append(a), nxt_l.append(nxt)
        obs = nxt
        if info["distance"] < tolerance:
            break


# ---------------------------------------------------------------------------- the paper's held-out set
def _static_tips(actions: np.ndarray, n_elements: int = 20, max_torque: float = 10.0,
                 bending_stiffness: float = 1e6 * np.pi * 0.05**4 / 4, length: float = 1.0) -> np.ndarray:
    """Approximate settled tips ``(M, 3)`` of held actions ``(M, 12)``: curvature = couple / EI
    along the rod (no shear, stretch or twist), integrated element by element. Used only to spread
    candidate actions over the workspace; targets are always the simulator's own settled tips."""
    basis = _spline_basis(n_elements - 1)
    kappa = max_torque / bending_stiffness * np.stack([actions[:, :6] @ basis.T, actions[:, 6:] @ basis.T], -1)
    ds = length / n_elements
    M = actions.shape[0]
    R = np.broadcast_to(np.eye(3), (M, 3, 3)).copy()
    p = np.zeros((M, 3))
    for j in range(n_elements):
        p += ds * R[:, :, 2]
        if j < n_elements - 1:
            w = np.concatenate([kappa[:, j], np.zeros((M, 1))], -1) * ds  # rotation vector in the local frame
            th = np.linalg.norm(w, axis=-1, keepdims=True)
            k = np.where(th > 1e-12, w / np.maximum(th, 1e-12), 0.0)
            K = np.zeros((M, 3, 3))
            K[:, 0, 1], K[:, 0, 2], K[:, 1, 0] = -k[:, 2], k[:, 1], k[:, 2]
            K[:, 1, 2], K[:, 2, 0], K[:, 2, 1] = -k[:, 0], -k[:, 1], k[:, 0]
            s, c = np.sin(th)[..., None], np.cos(th)[..., None]
            R = R @ (np.eye(3) + s * K + (1 - c) * (K @ K))
    return p


def workspace_goal_actions(n_targets: int, seed: int, pool: int = 20000, voxel: float = 0.05) -> np.ndarray:
    """``(n_targets, 12)`` held actions whose settled tips spread uniformly over the reachable
    workspace *volume*: a pool of candidate actions (i.i.d. uniform, coherent and linear bending
    profiles), their approximate tips binned in ``voxel`` cubes, occupied cubes drawn uniformly
    (not tips of uniform random actions, which cluster near rest)."""
    rng = np.random.default_rng(seed)
    k = pool // 3
    iid = rng.uniform(-1, 1, (k, 12))
    coherent = np.clip(np.repeat(rng.uniform(-1, 1, (k, 2)), 6, 1) + 0.3 * rng.normal(size=(k, 12)), -1, 1)
    ends = rng.uniform(-1, 1, (pool - 2 * k, 2, 2))
    linear = np.concatenate([np.linspace(ends[:, 0, 0], ends[:, 0, 1], 6).T, np.linspace(ends[:, 1, 0], ends[:, 1, 1], 6).T], 1)
    cand = np.concatenate([iid, coherent, linear])
    cells = np.floor(_static_tips(cand) / voxel).astype(np.int64)
    _, cell_of, counts = np.unique(cells, axis=0, return_inverse=True, return_counts=True)
    cell_of = cell_of.reshape(-1)
    chosen_cells = rng.choice(len(counts), size=n_targets, replace=n_targets > len(counts))
    return np.stack([cand[rng.choice(np.nonzero(cell_of == c)[0])] for c in chosen_cells])


def workspace_heldout(n_targets: int, seed: int, observed_points: int = 5, control_period: float = 0.1,
                      tolerance: float = 0.005, max_steps: int = 60, settle_steps: int = 20,
                      progress: bool = False) -> dict:
    """The paper's held-out protocol: ``n_targets`` targets spread uniformly over the reachable
    workspace volume (:func:`workspace_goal_actions`; each target is the simulator's settled tip of
    its action), each reached from rest by a fast controller (the command ramps to the target's
    action at rate 0.5 per step) and trimmed once the tip is within ``tolerance`` (5 mm).

    Returns numpy arrays ``observation``, ``action``, ``next_observation`` and ``targets`` (n, 3).
    """
    goals = workspace_goal_actions(n_targets, seed)
    env = SoftArmEnv(observed_points=observed_points, control_period=control_period, max_episode_steps=10**9)
    obs_l, act_l, nxt_l, targets = [], [], [], []
    it = range(n_targets)
    if progress:
        from tqdm.auto import tqdm

        it = tqdm(it, desc="held-out arm targets", unit="target", disable=None)  # no bar in a log file
    for i in it:
        targets.append(settle_tip(env, goals[i], steps=settle_steps))
        _reach(env, goals[i], targets[-1], 0.5, max_steps, tolerance, (obs_l, act_l, nxt_l))
    return {"observation": np.array(obs_l), "action": np.array(act_l), "next_observation": np.array(nxt_l),
            "targets": np.array(targets)}


def random_action_transitions(episodes: int, seed: int, observed_points: int = 5, control_period: float = 0.1,
                              steps: int = 200) -> dict:
    """Transitions of i.i.d. uniform actions from rest (the broad motion a Random explorer sees)."""
    rng = np.random.default_rng(seed)
    env = SoftArmEnv(observed_points=observed_points, control_period=control_period, max_episode_steps=steps)
    obs_l, act_l, nxt_l = [], [], []
    for _ in range(episodes):
        obs, _ = env.reset()
        for _ in range(steps):
            a = rng.uniform(-1, 1, 12).astype(np.float32)
            nxt, _, term, _, _ = env.step(a)
            if term:
                break
            obs_l.append(obs), act_l.append(a), nxt_l.append(nxt)
            obs = nxt
    return {"observation": np.array(obs_l), "action": np.array(act_l), "next_observation": np.array(nxt_l)}
