"""The PyElastica soft arm (SoftArm-v0 / SoftArm136-v0)."""
import numpy as np
import pytest
import torch

import torchrl_softae  # noqa: F401  (registers the gymnasium ids)
from torchrl_softae.envs.robots.soft_arm import (
    ARM_TARGET_ACTIONS,
    ARM_TARGETS,
    RampController,
    SoftArmEnv,
    arm_layout,
    reach_reward,
)


@pytest.fixture(scope="module")
def arm():
    return SoftArmEnv()


def test_table_s1_layouts():
    as_tuple = lambda lay: {k: (v.start, v.stop) for k, v in lay.items()}
    assert as_tuple(arm_layout(5)) == {"positions": (0, 15), "velocities": (15, 30), "orientations": (30, 46),
                                       "angular_velocities": (46, 58)}
    assert as_tuple(arm_layout(11)) == {"positions": (0, 33), "velocities": (33, 66), "orientations": (66, 106),
                                        "angular_velocities": (106, 136)}


def test_spaces_and_rest_observation_index_by_index(arm):
    assert arm.observation_space.shape == (58,) and arm.action_space.shape == (12,)
    assert SoftArmEnv(observed_points=11).observation_space.shape == (136,)
    obs, info = arm.reset(seed=0)
    pos = obs[0:15].reshape(5, 3)
    np.testing.assert_allclose(pos, [[0, 0, z] for z in (0, 0.25, 0.5, 0.75, 1.0)], atol=1e-6)  # evenly spaced points
    np.testing.assert_allclose(obs[15:30], 0, atol=1e-9)  # at rest
    quat = obs[30:46].reshape(4, 4)
    np.testing.assert_allclose(np.linalg.norm(quat, axis=1), 1, atol=1e-5)
    assert (quat[:, 0] >= 0).all()
    np.testing.assert_allclose(obs[46:58], 0, atol=1e-9)
    np.testing.assert_allclose(info["tip"], obs[12:15], atol=1e-6)


def test_bending_directions_and_tip_in_info(arm):
    arm.reset(seed=0)
    for _ in range(50):
        obs, r, term, trunc, info = arm.step(np.r_[np.zeros(6), np.ones(6)])  # binormal (d2) torque
    tip = obs[12:15]
    assert tip[0] > 0.3 and abs(tip[1]) < 1e-3 and tip[2] < 0.95  # bends in the x-z plane
    np.testing.assert_allclose(info["tip"], tip, atol=1e-6)
    w = obs[46:58].reshape(4, 3)
    assert np.abs(obs[15:30]).max() > 0  # moving
    assert np.isfinite(w).all()


def test_seeded_resets_are_deterministic():
    a, b = SoftArmEnv(task="reach-random"), SoftArmEnv(task="reach-random")
    oa, ia = a.reset(seed=3)
    ob, ib = b.reset(seed=3)
    np.testing.assert_array_equal(ia["target"], ib["target"])
    rng = np.random.default_rng(0)
    for _ in range(10):
        act = rng.uniform(-1, 1, 12)
        oa, *_ = a.step(act)
        ob, *_ = b.step(act)
    np.testing.assert_array_equal(oa, ob)


@pytest.mark.parametrize("direction", [np.r_[np.ones(6), np.zeros(6)], np.r_[-np.ones(6), np.zeros(6)],
                                       np.r_[np.zeros(6), np.ones(6)], np.r_[np.zeros(6), -np.ones(6)],
                                       np.ones(12), -np.ones(12)])
def test_no_nan_for_200_steps_at_max_torque(arm, direction):
    arm.reset(seed=0)
    for _ in range(200):
        obs, r, term, trunc, info = arm.step(direction)
        assert not term
    assert np.isfinite(obs).all() and not info["diverged"]


def test_no_nan_under_bang_bang_switching(arm):
    arm.reset(seed=0)
    rng = np.random.default_rng(1)
    for _ in range(200):
        obs, r, term, *_ = arm.step(np.sign(rng.uniform(-1, 1, 12)))
        assert not term
    assert np.isfinite(obs).all()


@pytest.mark.parametrize("task", ["reach-close", "reach-far"])
def test_both_targets_reachable_within_1cm(task):
    env = SoftArmEnv(task=task)
    obs, info = env.reset(seed=0)
    ctrl = RampController(ARM_TARGET_ACTIONS[task])
    best = np.inf
    for _ in range(200):
        obs, r, term, trunc, info = env.step(ctrl())
        best = min(best, info["distance"])
    assert best < 0.01, best
    assert r > 0.5  # g(d) close to 1 near the target
    np.testing.assert_allclose(info["target"], ARM_TARGETS[task])


def test_reach_reward_shape():
    assert reach_reward(0.0) == 1.0 and reach_reward(0.005) == 1.0
    d = np.array([0.01, 0.05, 0.2, 1.0])
    g = reach_reward(d)
    assert (np.diff(g) < 0).all() and (g > 0).all() and g[-1] > 0.01  # long tail
    torch.testing.assert_close(reach_reward(torch.tensor(d)), torch.tensor(g))


def test_divergence_is_detected_and_ends_episode():
    env = SoftArmEnv(max_torque=5e4)  # far beyond what the rod can take
    env.reset(seed=0)
    for k in range(200):
        obs, r, term, trunc, info = env.step(np.sign(np.sin(np.arange(12) + k)))
        if term:
            break
    assert term and info["diverged"]


def test_bad_actions_rejected(arm):
    arm.reset()
    with pytest.raises(ValueError, match="outside the action space"):
        arm.step(np.full(12, 2.0))
    with pytest.raises(ValueError, match="NaN"):
        arm.step(np.full(12, np.nan))


def test_render_rgb(arm):
    arm.reset()
    frame = arm.render()
    assert frame.ndim == 3 and frame.shape[2] == 3 and frame.dtype == np.uint8


def test_torchrl_gymenv_specs_and_gymnasium_checker():
    import gymnasium as gym
    from gymnasium.utils.env_checker import check_env
    from torchrl.envs import GymEnv
    from torchrl.envs.utils import check_env_specs

    for env_id, dim in (("SoftArm-v0", 58), ("SoftArm136-v0", 136)):
        env = GymEnv(env_id)
        check_env_specs(env)
        assert env.observation_spec["observation"].shape == (dim,)
    check_env(gym.make("SoftArm-v0", task="reach-close").unwrapped, skip_render_check=True)


def test_pipeline_explores_the_arm(tmp_path):
    from torchrl_softae.pipeline.cli import main
    from torchrl_softae.pipeline.runs import RunDir

    tiny = ["--set", "heldout_size=120", "--set", "model.num_cells=32", "--set", "model.depth=2",
            "--set", "planner.num_candidates=10", "--set", "planner.top_k=2", "--set", "planner.optim_steps=1",
            "--set", "train.epochs=2"]
    for method in ("softae", "random"):
        argv = ["explore", "--env", "SoftArm-v0", "--method", method, "--episodes", "1", "--episode-length", "10",
                "--run-dir", str(tmp_path / method), "--wandb", "disabled", "--quiet", *tiny]
        assert main(argv) == 0
        state = RunDir(tmp_path / method).load()
        assert state["num_transitions"] == 10 and state["history"][0]["heldout_nmse"] > 0
