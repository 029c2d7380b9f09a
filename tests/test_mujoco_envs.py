"""The MuJoCo fish (SoftFish-v0, SoftFishTarget-v0) and the HASEL-muscle leg (MSKLeg-v0)."""
import math

import numpy as np
import pytest

import torchrl_softae  # noqa: F401
from torchrl_softae.envs.robots.fish import SEGMENTS, SoftFishEnv, fish_layout
from torchrl_softae.envs.robots.msk_leg import HaselMuscleModel, MSKLegEnv, leg_layout

BODY_LENGTH = 2 * sum(s[1] for s in SEGMENTS)  # 0.48 m


def _swim(env, freq=3.0, phase=0.6, amp=1.0, bias=0.0, steps=200, seed=0):
    env.reset(seed=seed)
    for k in range(steps):
        t = 0.02 * k
        a = np.clip([amp * math.sin(2 * math.pi * freq * t - phase * i) + bias for i in range(4)], -1, 1)
        obs, r, term, trunc, info = env.step(a)
        assert not term
    return info["position"], info["yaw"], obs


def test_fish_table_s2_layout_index_by_index():
    as_t = lambda lay: {k: (v.start, v.stop) for k, v in lay.items()}
    assert as_t(fish_layout(False)) == {"velocity": (0, 3), "yaw": (3, 4), "yaw_rate": (4, 5),
                                        "joint_positions": (5, 10), "joint_velocities": (10, 15)}
    assert as_t(fish_layout(True)) == {"target": (0, 3), "velocity": (3, 6), "yaw": (6, 7), "yaw_rate": (7, 8),
                                       "joint_positions": (8, 13), "joint_velocities": (13, 18)}
    env = SoftFishEnv(with_target=True)
    obs, info = env.reset(seed=1)
    _swim(env, steps=20, seed=1)
    obs = env._obs()
    d = env.data
    np.testing.assert_allclose(obs[0:2], env.target[:2] - d.qpos[:2], atol=1e-6)  # target relative to head
    np.testing.assert_allclose(obs[3:5], d.qvel[:2], atol=1e-5)  # world-frame base velocity
    assert obs[5] == 0.0
    np.testing.assert_allclose(obs[6], d.qpos[2], atol=1e-6)  # yaw
    np.testing.assert_allclose(obs[7], d.qvel[2], atol=1e-5)
    np.testing.assert_allclose(obs[8:13], d.qpos[3:8], atol=1e-6)  # five joints, passive fin last
    np.testing.assert_allclose(obs[13:18], d.qvel[3:8], atol=1e-5)
    assert SoftFishEnv().observation_space.shape == (15,) and env.action_space.shape == (4,)


def test_travelling_wave_swims_forward_several_body_lengths():
    pos, yaw, _ = _swim(SoftFishEnv())
    assert pos[0] > 2 * BODY_LENGTH, pos


def test_reversed_wave_or_zero_torque_does_not_swim_forward():
    rev, _, _ = _swim(SoftFishEnv(), phase=-0.6)
    still, _, _ = _swim(SoftFishEnv(), amp=0.0)
    assert rev[0] < 0.1 * BODY_LENGTH, rev
    assert np.linalg.norm(still) < 0.01, still


def test_turning_gait_changes_heading_by_more_than_90_degrees():
    _, yaw, _ = _swim(SoftFishEnv(), freq=2.0, phase=0.8, bias=0.4)
    assert abs(yaw) > math.pi / 2, yaw


def test_fish_tasks_rewards_and_seeded_resets():
    env = SoftFishEnv(task="forward")
    a = _swim(env, steps=30, seed=4)[2]
    b = _swim(SoftFishEnv(task="forward"), steps=30, seed=4)[2]
    np.testing.assert_array_equal(a, b)
    env = SoftFishEnv(with_target=True, task="to-target")
    obs, info = env.reset(seed=0)
    _, r, *_ = env.step(np.zeros(4))
    assert r == pytest.approx(-np.linalg.norm(obs[:2]), abs=1e-3)
    with pytest.raises(ValueError, match="needs with_target=True"):
        SoftFishEnv(task="to-target")


def test_muscle_force_model():
    m = HaselMuscleModel()
    L0 = np.array([0.1])
    assert m.force(np.array([0.0]), L0, L0) == 0.0  # no voltage, no force
    at_max_strain = L0 * (1 - m.strain_max)
    assert m.force(np.array([m.v_max]), at_max_strain, L0) == 0.0  # fully zipped
    volts = np.linspace(0, m.v_max, 6)
    f = m.force(volts, np.full(6, 0.1), np.full(6, 0.1))
    assert (np.diff(f) > 0).all() and f[-1] == pytest.approx(m.f_max)
    np.testing.assert_allclose(f, m.f_max * (volts / m.v_max) ** 2)  # quadratic in V
    strains = np.linspace(0, m.strain_max, 5)
    fs = m.force(np.full(5, m.v_max), 0.1 * (1 - strains), np.full(5, 0.1))
    assert (np.diff(fs) < 0).all()  # weaker as it contracts
    v = np.zeros(1)
    for _ in range(int(5 * m.tau / 1e-4)):
        v = m.voltage_step(v, np.array([m.v_max]), 1e-4)
    assert 0.99 * m.v_max < v[0] <= m.v_max  # RC charging


def test_leg_table_s3_layout_index_by_index():
    env = MSKLegEnv()
    obs, info = env.reset(seed=0)
    for _ in range(5):
        obs, *_ = env.step(np.array([0.5, 1, -1, -1, 1]))
    d = env.data
    names = ("yaw", "pitch", "roll", "hip", "knee")
    for i, n in enumerate(names):
        assert obs[i] == pytest.approx(d.qpos[env.model.joint(n).qposadr[0]], abs=1e-6)
        assert obs[5 + i] == pytest.approx(d.qvel[env.model.joint(n).dofadr[0]], abs=1e-4)
    assert leg_layout()["boom_velocities"] == slice(5, 8) and obs.shape == (10,)
    assert env.action_space.shape == (5,)


def _hop(roll, steps=500, seed=0, freq=4.0, duty=0.4):
    env = MSKLegEnv()
    env.reset(seed=seed)
    for k in range(steps):
        stance = (0.01 * k * freq) % 1.0 < duty
        # knee extensor during stance, flexor during swing; hip muscles idle
        a = np.array([roll, -1.0, -1.0, -1.0 if stance else 1.0, 1.0 if stance else -1.0])
        obs, r, term, trunc, info = env.step(a)
        assert not term
    return info["yaw"]


def test_scripted_hopping_goes_ccw_or_cw_with_the_motor_roll():
    ccw, cw = _hop(+1.0), _hop(-1.0)
    assert ccw > 0.3, ccw  # counter-clockwise around the post
    assert cw < -0.3, cw


def test_divergence_flagged(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # MuJoCo logs the instability to ./MUJOCO_LOG.TXT
    for env in (SoftFishEnv(), MSKLegEnv()):
        env.reset(seed=0)
        env.data.qvel[:] = 1e12
        *_, term, trunc, info = env.step(np.zeros(env.action_space.shape))
        assert term and info["diverged"]


@pytest.mark.rendering
def test_render_offscreen():
    from conftest import render_or_skip

    for env in (SoftFishEnv(), MSKLegEnv()):
        env.reset(seed=0)
        frame = render_or_skip(env)
        assert frame.shape == (240, 320, 3) and frame.dtype == np.uint8 and frame.std() > 0
        env.close()


@pytest.mark.parametrize("env_id", ["SoftFish-v0", "SoftFishTarget-v0", "MSKLeg-v0"])
def test_specs_checkers_and_pipeline(env_id, tmp_path):
    import gymnasium as gym
    from gymnasium.utils.env_checker import check_env
    from torchrl.envs import GymEnv
    from torchrl.envs.utils import check_env_specs

    from torchrl_softae.pipeline.cli import main
    from torchrl_softae.pipeline.catalog import get_env_entry
    from torchrl_softae.pipeline.runs import RunDir

    check_env_specs(GymEnv(env_id))
    check_env_specs(get_env_entry(env_id).make())
    check_env(gym.make(env_id).unwrapped, skip_render_check=True)
    tiny = ["--set", "heldout_size=200", "--set", "model.num_cells=32", "--set", "model.depth=2",
            "--set", "planner.num_candidates=10", "--set", "planner.top_k=2", "--set", "planner.optim_steps=1",
            "--set", "planner.horizon=5", "--set", "train.epochs=2"]
    for method in ("random", "softae"):
        argv = ["explore", "--env", env_id, "--method", method, "--episodes", "1", "--episode-length", "20",
                "--run-dir", str(tmp_path / method), "--wandb", "disabled", "--quiet", *tiny]
        assert main(argv) == 0
        state = RunDir(tmp_path / method).load()
        assert state["num_transitions"] == 20 and 0 < state["history"][0]["coverage"] <= 1
    task = sorted(get_env_entry(env_id).tasks)[0]
    assert main(["evaluate", "--run-dir", str(tmp_path / "softae"), "--task", task, "--episodes", "1", "--quiet"]) == 0
