import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Bounded
from torchrl.envs import Compose, TransformedEnv
from torchrl.envs.utils import check_env_specs

from torchrl_softae.envs import EnsembleModelEnv, HallucinatedControl, UncertaintyReward
from torchrl_softae.modules import EnsembleWorldModel


@pytest.fixture
def model():
    m = EnsembleWorldModel(4, 2, num_cells=32, depth=2)
    obs = torch.randn(200, 4)
    m.fit_normalizers(obs, torch.rand(200, 2) * 2 - 1, obs + 0.1 * torch.randn(200, 4))
    return m


@pytest.mark.parametrize("mode", ["mean", "sample", "optimistic"])
def test_specs_with_and_without_transforms(model, mode):
    env = EnsembleModelEnv(model, mode=mode)
    check_env_specs(env)
    check_env_specs(TransformedEnv(env, UncertaintyReward()))
    if mode == "optimistic":
        hc = HallucinatedControl(beta=2.0)
        tenv = TransformedEnv(EnsembleModelEnv(model, mode=mode), Compose(hc, UncertaintyReward()))
        check_env_specs(tenv)
        assert tenv.action_spec.shape == (2 + 4,)
        assert (tenv.action_spec.space.low[2:] == -1).all() and (tenv.action_spec.space.high[2:] == 1).all()
        assert "eta" not in tenv.full_action_spec.keys()


def test_optimistic_eta_plus_one_moves_prediction_by_beta_sigma(model):
    beta = 2.0
    tenv = TransformedEnv(EnsembleModelEnv(model, mode="optimistic"), HallucinatedControl(beta=beta))
    obs, act = torch.randn(16, 4), torch.rand(16, 2) * 2 - 1
    mu, sigma, _, _ = model.predict(obs, act)
    for sign in (1.0, -1.0, 0.0):
        td = TensorDict({"observation": obs, "action": torch.cat([act, torch.full((16, 4), sign)], -1)}, [16])
        nxt = tenv.step(td)["next", "observation"]
        torch.testing.assert_close(nxt - mu, sign * beta * sigma)
    # the real action reaching the model is the first d_a dims; the caller's tensordict is untouched
    assert td["action"].shape == (16, 6)


def test_mean_and_sample_modes(model):
    obs, act = torch.randn(10, 4), torch.rand(10, 2) * 2 - 1
    mu, sigma, _, members = model.predict(obs, act)
    out = EnsembleModelEnv(model, mode="mean").step(TensorDict({"observation": obs, "action": act}, [10]))
    torch.testing.assert_close(out["next", "observation"], mu)
    torch.testing.assert_close(out["next", "epistemic_std"], sigma)
    env = EnsembleModelEnv(model, mode="sample", aleatoric_noise=False)
    assert not env.deterministic and EnsembleModelEnv(model, mode="mean").deterministic
    idx = torch.arange(10) % 5
    out = env.step(TensorDict({"observation": obs, "action": act, "member_index": idx}, [10]))
    torch.testing.assert_close(out["next", "observation"], members[idx, torch.arange(10)])
    # member assignment is carried through a rollout (trajectory sampling, TS-inf)
    roll = env.rollout(5, auto_reset=True)
    assert (roll["member_index"] == roll["member_index"][:1]).all()


def test_aleatoric_noise_is_seeded(model):
    env = EnsembleModelEnv(model, mode="sample")
    td = TensorDict({"observation": torch.randn(3, 4), "action": torch.zeros(3, 2), "member_index": torch.zeros(3, dtype=torch.long)}, [3])
    env.set_seed(3)
    a = env.step(td.clone())["next", "observation"]
    env.set_seed(3)
    b = env.step(td.clone())["next", "observation"]
    torch.testing.assert_close(a, b)


def test_uncertainty_reward_norms_and_scale(model):
    env = TransformedEnv(EnsembleModelEnv(model), UncertaintyReward())
    td = TensorDict({"observation": torch.randn(7, 4), "action": torch.rand(7, 2) * 2 - 1}, [7])
    td = env.step(td)
    sigma = td["next", "epistemic_std"]
    torch.testing.assert_close(td["next", "reward"], sigma.norm(dim=-1, keepdim=True))
    scale = torch.tensor([1.0, 2.0, 4.0, 8.0])
    r = UncertaintyReward(ord=1, scale=scale).reward_from_sigma(sigma)
    torch.testing.assert_close(r, (sigma / scale).abs().sum(-1, keepdim=True))
    with pytest.raises(ValueError, match="scale must be positive"):
        UncertaintyReward(scale=torch.tensor([1.0, 0.0, 1.0, 1.0])).set_scale(torch.tensor([1.0, 0.0, 1.0, 1.0]))
    with pytest.raises(ValueError, match="ord=-1"):
        UncertaintyReward(ord=-1)


@pytest.mark.parametrize("beta", [-0.5, float("nan"), float("inf")])
def test_negative_or_invalid_beta_rejected(beta):
    with pytest.raises(ValueError, match="beta="):
        HallucinatedControl(beta=beta)


def test_bad_inputs_name_the_value(model):
    tenv = TransformedEnv(EnsembleModelEnv(model, mode="optimistic"), HallucinatedControl())
    with pytest.raises(ValueError, match=r"expected \(\.\.\., 6\)"):
        tenv.step(TensorDict({"observation": torch.randn(2, 4), "action": torch.zeros(2, 2)}, [2]))
    env = EnsembleModelEnv(model)
    with pytest.raises(ValueError, match="outside the action spec"):
        env.step(TensorDict({"observation": torch.randn(2, 4), "action": torch.full((2, 2), 3.0)}, [2]))
    with pytest.raises(ValueError, match="mode='ucb'"):
        EnsembleModelEnv(model, mode="ucb")
    with pytest.raises(ValueError, match="expected \\(2,\\)"):
        EnsembleModelEnv(model, action_spec=Bounded(-1, 1, (3,)))
    with pytest.raises(KeyError, match="mode='optimistic'"):
        HallucinatedControl().transform_input_spec(EnsembleModelEnv(model, mode="mean").input_spec)


def test_policy_for_real_env_strips_eta(model):
    from torchrl_softae.modules import ICEMPlanner

    hc = HallucinatedControl()
    tenv = TransformedEnv(EnsembleModelEnv(model, mode="optimistic"), Compose(hc, UncertaintyReward()))
    planner = ICEMPlanner(tenv, planning_horizon=3, optim_steps=2, num_candidates=16, top_k=4)
    policy = hc.policy_for_real_env(planner)
    out = policy(TensorDict({"observation": torch.randn(5, 4)}, [5]))
    assert out["action"].shape == (5, 2)
    assert (out["action"].abs() <= 1).all()
