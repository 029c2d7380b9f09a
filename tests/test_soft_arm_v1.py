"""SoftArm-v1: a control period the planner can see through, far but reachable targets, the
paper's held-out protocol (workspace-volume targets) and a metric normalized by a reference set."""
import numpy as np
import pytest
import torch
from tensordict import TensorDict

from torchrl_softae.envs.robots.soft_arm import (
    ARM_TARGET_ACTIONS_V1,
    ARM_TARGETS_V1,
    RampController,
    SoftArmEnv,
    _static_tips,
    step_response,
    workspace_goal_actions,
    workspace_heldout,
)
from torchrl_softae.pipeline.data import reference_scale, trivial_nmse

REST = np.array([0.0, 0.0, 1.0])


@pytest.fixture(scope="module")
def arm():
    return SoftArmEnv(control_period=0.1, target_set="v1")


def test_step_response_fits_the_planning_horizon(arm):
    r = step_response(arm, np.r_[np.ones(6), np.zeros(6)], steps=40)
    assert 0.8 < r["final_m"] < 0.95
    assert 7 <= r["rise_steps"] <= 11, r  # measured 9 (10-90 %)
    assert r["settle_steps"] <= 14, r  # measured 12 (5 %): H = 10 spans most of it
    assert r["overshoot"] < 0.05


@pytest.mark.parametrize("task", ["reach-close", "reach-far"])
def test_v1_targets_are_reached_by_a_scripted_controller(arm, task):
    arm.reset(options={"target": ARM_TARGETS_V1[task]})
    ctrl = RampController(ARM_TARGET_ACTIONS_V1[task], rate=0.5)
    best = min(arm.step(ctrl())[4]["distance"] for _ in range(40))
    assert best < 0.01, best


def test_far_target_is_far_and_needs_coordinated_bending():
    assert 0.25 < np.linalg.norm(ARM_TARGETS_V1["reach-close"] - REST) < 0.35
    assert 0.58 < np.linalg.norm(ARM_TARGETS_V1["reach-far"] - REST) < 0.7
    # every uniform bending profile (the same couple at all control points, any direction)
    c = np.linspace(-1, 1, 81)
    uniform = np.array([np.r_[np.full(6, a), np.full(6, b)] for a in c for b in c])
    gap = np.linalg.norm(_static_tips(uniform) - ARM_TARGETS_V1["reach-far"], axis=1).min()
    assert gap > 0.04, gap  # 6 cm; the approximate statics are within ~1 cm of the simulator


def test_heldout_targets_cover_the_workspace_volume():
    tips = _static_tips(workspace_goal_actions(300, seed=0))
    dist = np.linalg.norm(tips - REST, axis=1)
    assert np.median(dist) >= 0.4 * dist.max(), (np.median(dist), dist.max())  # measured 0.73 vs 1.07 m
    hist = np.histogram(dist, bins=5, range=(0, dist.max()))[0]
    assert hist[0] < 0.3 * len(dist)  # not concentrated near rest


def test_heldout_rollouts_reach_their_targets_and_are_trimmed():
    d = workspace_heldout(3, seed=0)
    assert d["targets"].shape == (3, 3) and d["observation"].shape[1] == 58
    assert 3 <= len(d["action"]) <= 3 * 60
    final_tips = d["next_observation"][:, 12:15]
    assert min(np.linalg.norm(final_tips - t, axis=1).min() for t in d["targets"]) < 0.005


def _ref(n=500, d=6, seed=0):
    g = torch.Generator().manual_seed(seed)
    obs = torch.randn(n, d, generator=g)
    return TensorDict({"observation": obs, "action": torch.zeros(n, 1),
                       ("next", "observation"): obs + 0.3 * torch.randn(n, d, generator=g)}, [n])


def test_metric_scores_one_for_the_reference_mean_and_ignores_constant_dimensions():
    ref = _ref()
    scale = reference_scale(ref)
    res = trivial_nmse(ref, scale, {"first": [0, 1]})
    assert res["mean"][0] == pytest.approx(1.0, abs=1e-5) and res["mean"][1]["first"] == pytest.approx(1.0, abs=1e-5)
    assert 0 < res["identity"][0] < 1
    # a constant dimension changes nothing
    const = ref.clone()
    const["observation"] = torch.cat([ref["observation"], torch.full((500, 1), 3.0)], -1)
    const["next", "observation"] = torch.cat([ref["next", "observation"], torch.full((500, 1), 3.0)], -1)
    res2 = trivial_nmse(const, reference_scale(const), {"first": [0, 1]})
    assert res2["mean"][0] == pytest.approx(res["mean"][0], rel=1e-6)
    assert res2["identity"][0] == pytest.approx(res["identity"][0], rel=1e-6)
