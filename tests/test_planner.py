import math

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import Compose, TransformedEnv
from torchrl.modules import CEMPlanner

from _envs import PointMassEnv
from torchrl_softae.envs import EnsembleModelEnv, HallucinatedControl, UncertaintyReward
from torchrl_softae.modules.planners import rollout_returns
from torchrl_softae.modules import EnsembleWorldModel, ICEMPlanner, MPPIPlanner, colored_noise, resolve_planning_dtype
from torchrl_softae.modules.engine.paths import INFERENCE_PATHS


def test_colored_noise_unit_variance_and_correlation():
    g = torch.Generator().manual_seed(0)
    white = colored_noise(0.0, (4000, 64), generator=g)
    red = colored_noise(2.0, (4000, 64), generator=g)
    for x in (white, red):
        assert abs(float(x.std()) - 1.0) < 0.2
    lag1 = lambda x: float((x[:, 1:] * x[:, :-1]).mean() / x.var())
    assert abs(lag1(white)) < 0.05
    assert lag1(red) > 0.8
    a = colored_noise(0.25, (3, 10), generator=torch.Generator().manual_seed(1))
    b = colored_noise(0.25, (3, 10), generator=torch.Generator().manual_seed(1))
    torch.testing.assert_close(a, b)
    with pytest.raises(ValueError, match="exponent=-1"):
        colored_noise(-1, (2, 3))


def test_colored_noise_basis_matches_the_fft():
    """The planners' short series come from a fixed matrix of the Gaussian coefficients, long ones
    from the inverse FFT: the same values from the same draws (fp32 rounding), even and odd T,
    fp32 and fp64, and either form has unit variance."""
    import importlib

    # the module (the package exports the function under its name)
    module = importlib.import_module("torchrl_softae.modules.planners.colored_noise")

    for T in (2, 5, 10, 64):
        for dtype in (torch.float32, torch.float64):
            fast = module._by_basis(0.25, (300, T), torch.Generator().manual_seed(T), dtype, "cpu")
            fft = module._by_fft(0.25, (300, T), torch.Generator().manual_seed(T), dtype, "cpu")
            assert fast.dtype == fft.dtype == dtype
            torch.testing.assert_close(fast, fft, rtol=1e-5, atol=1e-5)
    long = colored_noise(1.0, (500, module.MAX_BASIS_T + 1), generator=torch.Generator().manual_seed(0))
    short = colored_noise(1.0, (500, module.MAX_BASIS_T), generator=torch.Generator().manual_seed(0))
    for x in (long, short):
        assert abs(float(x.std()) - 1.0) < 0.2


def test_icem_finds_analytic_optimum():
    target = torch.tensor([0.6, -0.3])
    env = PointMassEnv(2, target)
    planner = ICEMPlanner(env, planning_horizon=3, optim_steps=10, num_particles=1, seed=0)
    action = planner(TensorDict({"observation": torch.zeros(2)}, []))["action"]
    # optimum: reach the target with the first action (return 0), then stay
    assert (action - target).abs().max() < 0.05, action
    assert float(planner.last_info["best_return"]) > -0.01


def _closed_loop(planner, env, steps=6):
    s, ret = torch.zeros(env.target.shape), 0.0
    for _ in range(steps):
        s = s + planner(TensorDict({"observation": s}, []))["action"]
        ret -= float((s - env.target).square().sum())
    return ret


def test_icem_beats_torchrl_cem_at_equal_budget():
    wins, icem_total, cem_total = 0, 0.0, 0.0
    for seed in range(20):
        torch.manual_seed(seed)
        env = PointMassEnv(2, torch.rand(2) * 4 - 2)
        icem = ICEMPlanner(env, planning_horizon=5, optim_steps=3, num_candidates=32, top_k=4, num_particles=1, seed=seed)
        cem = CEMPlanner(env, planning_horizon=5, optim_steps=3, num_candidates=32, top_k=4)
        torch.manual_seed(seed)
        r_icem = _closed_loop(icem, env)
        torch.manual_seed(seed)
        r_cem = _closed_loop(cem, env)
        wins += r_icem > r_cem
        icem_total += r_icem
        cem_total += r_cem
    assert wins >= 14, wins
    assert icem_total > cem_total


def test_nan_return_never_wins():
    env = PointMassEnv(1, torch.tensor([1.0]), nan_region=True)  # a > 0.5 gives NaN reward
    planner = ICEMPlanner(env, planning_horizon=1, num_particles=1, seed=0)
    a = planner(TensorDict({"observation": torch.zeros(1)}, []))["action"]
    assert float(a) <= 0.5 and float(a) > 0.4  # best finite action is at the NaN border
    assert math.isfinite(float(planner.last_info["best_return"]))


def test_batched_initial_states_each_get_their_own_plan():
    target = torch.tensor([0.0, 0.0])
    env = PointMassEnv(2, target)
    planner = ICEMPlanner(env, planning_horizon=2, optim_steps=10, num_particles=1, seed=0)
    starts = torch.tensor([[0.5, 0.5], [-0.4, 0.2], [0.1, -0.7]]).reshape(3, 1, 2)
    action = planner(TensorDict({"observation": starts}, [3, 1]))["action"]
    assert action.shape == (3, 1, 2)
    assert (action + starts).abs().max() < 0.05  # each moves its own state onto the target


def _model_env(mode, **kw):
    m = EnsembleWorldModel(3, 2, num_cells=16, depth=2)
    obs = torch.randn(100, 3)
    m.fit_normalizers(obs, torch.rand(100, 2) * 2 - 1, obs + 0.1 * torch.randn(100, 3))
    return EnsembleModelEnv(m, mode=mode, **kw)


def test_deterministic_propagation_does_not_recompute_identical_particles():
    tenv = TransformedEnv(_model_env("optimistic"), Compose(HallucinatedControl(), UncertaintyReward()))
    fast = ICEMPlanner(tenv, planning_horizon=4, num_particles=10)
    full = ICEMPlanner(tenv, planning_horizon=4, num_particles=10, deduplicate_particles=False)
    assert fast.effective_particles == 1 and full.effective_particles == 10
    obs = TensorDict({"observation": torch.randn(2, 3)}, [2])
    acts = torch.rand(2, 7, 4, 5) * 2 - 1
    torch.testing.assert_close(fast.evaluate(obs, acts), full.evaluate(obs, acts))
    # stochastic propagation keeps every particle
    assert ICEMPlanner(TransformedEnv(_model_env("sample"), UncertaintyReward()), num_particles=10).effective_particles == 10


def test_sample_mode_particles_follow_distinct_members():
    env = TransformedEnv(_model_env("sample", aleatoric_noise=False), UncertaintyReward())
    planner = ICEMPlanner(env, planning_horizon=3, num_particles=5, seed=0)
    obs = TensorDict({"observation": torch.randn(1, 3)}, [1])
    acts = torch.zeros(1, 1, 3, 2)
    r1 = planner.evaluate(obs, acts)
    # returns average over particles that follow different members -> not a single member's return
    assert torch.isfinite(r1).all()


@pytest.mark.parametrize("path", INFERENCE_PATHS)
def test_bf16_ranking_matches_fp32(path):
    from scipy.stats import spearmanr

    tenv = TransformedEnv(_model_env("optimistic"), Compose(HallucinatedControl(), UncertaintyReward()))
    # give the ensemble a real disagreement structure: train briefly on data
    from torchrl_softae.objectives import EnsembleLoss, EnsembleTrainer

    x = torch.rand(400, 3) * 2 - 1
    a = torch.rand(400, 2) * 2 - 1
    td = TensorDict({"observation": x, "action": a, ("next", "observation"): x + 0.3 * torch.sin(3 * a[:, :1] + x)}, [400])
    EnsembleTrainer(EnsembleLoss(tenv.base_env.world_model), lr=3e-3, epochs=20).fit(td)
    if path not in tenv.base_env.world_model.engine.available_inference_paths(torch.bfloat16):
        pytest.skip(f"{path} does not run in bf16 here (its kernel not built or not supported by this CPU, or "
                    "conv-fused without oneDNN's bf16 convolution: test_ensemble checks the error)")
    model = tenv.base_env.world_model
    fp32 = ICEMPlanner(tenv, planning_horizon=5)
    bf16 = ICEMPlanner(tenv, planning_horizon=5, precision="bf16")
    obs = TensorDict({"observation": torch.rand(1, 3) * 2 - 1}, [1])
    acts = torch.rand(1, 300, 5, 5) * 2 - 1
    # every kernel path keeps the ranking (the fp32 reference on the same path where it runs in fp32;
    # amx-network is bf16 only, fma-network runs both)
    model.engine.inference_path = path if path in model.engine.available_inference_paths(torch.float32) else "auto"
    r32 = fp32.evaluate(obs, acts)
    model.engine.inference_path = path
    r16 = bf16.evaluate(obs, acts)
    assert tenv.base_env._plan_dtype is None  # the precision lived for one plan only, on the env, never on the model
    assert not torch.equal(r32, r16)  # the reduced-precision path really ran
    rho = spearmanr(r32[0].numpy(), r16[0].numpy()).statistic
    assert rho >= 0.95, rho


def test_time_budget_returns_best_so_far(monkeypatch):
    """Anytime mode stops before an iteration that would overrun the budget and acts on the best
    sequence so far. The planner's clock is the test's, moved 12 ms by every candidate evaluation,
    so the count does not depend on this machine's speed: 4 iterations fit in 50 ms, a fifth would
    end at 60."""
    from types import SimpleNamespace

    from torchrl_softae.modules.planners import icem

    clock = [0.0]
    monkeypatch.setattr(icem, "time", SimpleNamespace(perf_counter=lambda: clock[0]))
    tenv = TransformedEnv(_model_env("optimistic"), Compose(HallucinatedControl(), UncertaintyReward()))
    planner = ICEMPlanner(tenv, planning_horizon=10, optim_steps=50, num_candidates=200, time_budget=0.05)
    evaluate = planner.evaluate

    def evaluate_taking_12_ms(*args, **kwargs):
        clock[0] += 0.012
        return evaluate(*args, **kwargs)

    planner.evaluate = evaluate_taking_12_ms
    out = planner(TensorDict({"observation": torch.randn(3)}, []))
    assert planner.last_info["iterations"] == 4
    assert out["action"].shape == (5,)


def test_warm_start_shift_and_reset():
    env = PointMassEnv(2, torch.tensor([0.3, 0.3]))
    planner = ICEMPlanner(env, planning_horizon=4, num_particles=1, num_candidates=20, top_k=4)
    td = TensorDict({"observation": torch.zeros(2)}, [])
    planner(td)
    assert planner._mean.shape == (1, 4, 2) and torch.equal(planner._mean[:, -1], torch.zeros(1, 2))
    planner(TensorDict({"observation": torch.zeros(2), "is_init": torch.ones(1, dtype=torch.bool)}, []))
    planner.reset()
    assert planner._mean is None and planner._elites is None


@pytest.mark.parametrize("kind", [ICEMPlanner, MPPIPlanner])
def test_a_planner_given_another_ones_search_state_takes_the_same_actions(kind):
    """``search_state`` holds all a call depends on besides its input (the warm start, the
    planner's generator and the model env's, which trajectory sampling's aleatoric noise draws
    from): a second planner, seeded otherwise, loaded with it continues the first one's episode."""
    torch.manual_seed(0)
    model_env = _model_env("sample", aleatoric_noise=True)
    env = TransformedEnv(model_env, UncertaintyReward())
    settings = dict(planning_horizon=4, num_candidates=16, num_particles=3, optim_steps=2, seed=0)
    if kind is ICEMPlanner:
        settings["top_k"] = 4
    first = kind(env, **settings)
    states = [TensorDict({"observation": torch.randn(2, 3)}, [2]) for _ in range(4)]
    first(states[0].clone())
    state = first.search_state()
    assert state["evaluator_generator"] is not None and all(v is not None for v in state["warm_start"].values())
    ahead = [first(td.clone())["action"] for td in states[1:]]

    second = kind(TransformedEnv(_model_env("sample", aleatoric_noise=True), UncertaintyReward()), **{**settings, "seed": 9})
    second.env.base_env.world_model.load_state_dict(model_env.world_model.state_dict())
    second.env.base_env.set_seed(5)
    second.load_search_state(state)
    for td, action in zip(states[1:], ahead):
        assert torch.equal(second(td.clone())["action"], action)
    # without the state the same calls plan otherwise (the test can tell)
    third = kind(env, **{**settings, "seed": 9})
    assert not torch.equal(third(states[1].clone())["action"], ahead[0])
    third.reset()
    assert all(getattr(third, name) is None for name in third._warm_start)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(planning_horizon=-1), "planning_horizon=-1"),
        (dict(top_k=300), "top_k=300"),
        (dict(elite_fraction=1.5), "elite_fraction=1.5"),
        (dict(precision="fp8"), "precision='fp8'"),
        (dict(time_budget=0), "time_budget=0"),
    ],
)
def test_bad_planner_settings(kwargs, match):
    with pytest.raises(ValueError, match=match):
        ICEMPlanner(PointMassEnv(2, torch.zeros(2)), **kwargs)


def test_bad_observation_rejected():
    planner = ICEMPlanner(PointMassEnv(2, torch.zeros(2)), num_candidates=10, top_k=2)
    with pytest.raises(ValueError, match="'observation' contains NaN"):
        planner(TensorDict({"observation": torch.tensor([0.0, float("nan")])}, []))
    with pytest.raises(ValueError, match=r"expected \(\.\.\., 2\)"):
        planner(TensorDict({"observation": torch.zeros(3)}, []))


@pytest.mark.parametrize("mode", ["mean", "optimistic"])
def test_model_env_contract_matches_torchrl_generic_rollout(mode):
    """The model env's evaluate_action_sequences scores sequences exactly as TorchRL's generic
    env.rollout over the same transformed env does (deterministic modes)."""
    tenv = TransformedEnv(_model_env(mode), Compose(HallucinatedControl(), UncertaintyReward())) if mode == "optimistic" \
        else TransformedEnv(_model_env(mode), UncertaintyReward())
    obs = TensorDict({"observation": torch.randn(2, 3)}, [2])
    d = tenv.action_spec.shape[-1]
    acts = torch.rand(2, 6, 4, d) * 2 - 1
    contract = tenv.base_env.evaluate_action_sequences(obs, acts, num_particles=1, env=tenv)
    generic = rollout_returns(tenv, obs, acts, num_particles=1)
    torch.testing.assert_close(contract, generic)


def test_evaluate_action_sequences_refuses_sequences_outside_the_action_spec():
    """Uniform bounds (the one-pass check) and per-dimension bounds (the fallback) alike: at the
    bounds is inside, a hair beyond them is outside."""
    from torchrl_softae.envs.model_env import _leaves_box

    tenv = TransformedEnv(_model_env("optimistic"), Compose(HallucinatedControl(), UncertaintyReward()))
    obs = TensorDict({"observation": torch.randn(1, 3)}, [1])
    d = tenv.action_spec.shape[-1]
    at_bounds = torch.rand(1, 4, 3, d).round() * 2 - 1  # only -1 and 1
    assert torch.isfinite(tenv.base_env.evaluate_action_sequences(obs, at_bounds, num_particles=1, env=tenv)).all()
    beyond = at_bounds.clone()
    beyond[0, 2, 1, d - 1] = 1.001
    with pytest.raises(ValueError, match="leave the action spec"):
        tenv.base_env.evaluate_action_sequences(obs, beyond, num_particles=1, env=tenv)
    low, high = torch.tensor([-1.0, 0.0, -2.0]), torch.tensor([1.0, 0.5, 2.0])
    x = torch.tensor([[0.9, 0.5, -2.0], [-1.0, 0.0, 1.9]])
    assert not _leaves_box(x, low, high)
    for i, j, v in ((0, 1, 0.51), (1, 1, -0.01), (0, 0, 1.01), (1, 2, -2.01)):
        y = x.clone()
        y[i, j] = v
        assert _leaves_box(y, low, high), (i, j, v)
    assert not _leaves_box(torch.full((2, 3), 0.25), low, high)  # the one-pass check alone decides


def test_a_second_planner_plans_through_the_same_contract():
    """MPPI uses the model env's evaluator (no getattr probing) and the generic path elsewhere."""
    tenv = TransformedEnv(_model_env("optimistic"), Compose(HallucinatedControl(), UncertaintyReward()))
    mppi = MPPIPlanner(tenv, planning_horizon=3, num_candidates=32, num_particles=10, seed=0)
    icem = ICEMPlanner(tenv, planning_horizon=3, num_candidates=32, top_k=4, num_particles=10, seed=0)
    assert mppi.evaluator is tenv.base_env and icem.evaluator is tenv.base_env
    assert mppi.effective_particles == icem.effective_particles == 1  # the env says: deterministic
    obs = TensorDict({"observation": torch.randn(2, 3)}, [2])
    acts = torch.rand(2, 5, 3, 5) * 2 - 1
    torch.testing.assert_close(mppi.evaluate(obs, acts), icem.evaluate(obs, acts))
    out = mppi(TensorDict({"observation": torch.randn(4, 3)}, [4]))["action"]
    assert out.shape == (4, 5) and out.abs().max() <= 1
    # a generic env (no contract): MPPI finds the analytic optimum of the point mass
    target = torch.tensor([0.6, -0.3])
    planner = MPPIPlanner(PointMassEnv(2, target), planning_horizon=2, optim_steps=10, num_candidates=256, noise_std=0.2,
                          temperature=0.01, num_particles=1, seed=0)
    assert planner.evaluator is None
    a = planner(TensorDict({"observation": torch.zeros(2)}, []))["action"]
    assert (a - target).abs().max() < 0.1, a


def test_torchrl_mppi_plans_over_the_model_env():
    """TorchRL's own MPPIPlanner runs over the same model env stack (through env.rollout)."""
    from torchrl.envs.utils import RandomPolicy  # noqa: F401
    from torchrl.modules import MPPIPlanner as TorchRLMPPI
    from torchrl.modules import ValueOperator
    from torchrl.objectives.value import TDLambdaEstimator

    tenv = TransformedEnv(_model_env("mean"), UncertaintyReward())
    value = ValueOperator(torch.nn.Linear(3, 1), in_keys=["observation"])
    planner = TorchRLMPPI(tenv, TDLambdaEstimator(gamma=0.99, lmbda=0.95, value_network=value),
                          temperature=1.0, planning_horizon=3, optim_steps=2, num_candidates=16, top_k=4)
    with torch.no_grad():
        a = planner(TensorDict({"observation": torch.randn(3)}, []))["action"]
    assert a.shape == (2,) and a.abs().max() <= 1


def test_rollouts_match_the_torchrl_stack():
    """A plan is scored by the engine's rollout where one applies (deterministic with one particle,
    trajectory sampling with several), as prepared kernel calls on a whole-network path and as torch
    ops elsewhere, and gives exactly what stepping the TorchRL stack gives, noise draws included;
    every other plan (noisy mean or optimistic particles, one sampled particle, rollouts switched
    off, a stack with a transform the model env does not know) is scored by stepping."""
    from torchrl.envs import RewardScaling

    from torchrl_softae.tasks import Task, TaskReward

    task = Task("t", lambda s, a, s2: -(s2 - 0.3).square().sum(-1) - 0.1 * a.square().sum(-1), 4)
    cases = [  # (model env, transforms, particles, the rollout that scores it)
        (_model_env("mean"), [UncertaintyReward()], 1, "deterministic"),
        (_model_env("optimistic"), [HallucinatedControl(beta=1.5), UncertaintyReward()], 1, "deterministic"),
        (_model_env("optimistic"), [HallucinatedControl(beta=2.0), TaskReward(task, action_dim=2)], 1, "deterministic"),
        (_model_env("sample", aleatoric_noise=False), [UncertaintyReward()], 3, "sampled"),
        (_model_env("sample"), [UncertaintyReward()], 3, "sampled"),
        (_model_env("sample"), [TaskReward(task, action_dim=2)], 4, "sampled"),
        (_model_env("sample"), [UncertaintyReward()], 1, None),
        (_model_env("optimistic", aleatoric_noise=True), [HallucinatedControl(beta=2.0), TaskReward(task, action_dim=2)], 3, None),
        (_model_env("mean", aleatoric_noise=True), [UncertaintyReward()], 2, None),
    ]
    for base, transforms, particles, kind in cases:
        tenv = TransformedEnv(base, Compose(*transforms))
        assert base._tensor_stack(tenv) is not None
        member = torch.arange(particles).expand(2, 5, particles) % 5 if particles > 1 else None
        assert base._rollout_kind(particles, member) == kind
        base.world_model.engine.rollouts = False
        assert base._rollout_kind(particles, member) is None
        base.world_model.engine.rollouts = True
        if kind is None:
            continue
        d = tenv.action_spec.shape[-1]
        obs = torch.randn(2, 1, 1, 3).expand(2, 5, particles, 3)
        acts = (torch.rand(2, 5, 1, 4, d) * 2 - 1).expand(2, 5, particles, 4, d)
        base.set_seed(0)
        slow = base._returns_through_step(tenv, obs, acts, member)
        base.set_seed(0)
        torch.testing.assert_close(base._returns_by_rollout(kind, base._tensor_stack(tenv), obs, acts[:, :, 0], member),
                                   slow)
        cache_kind = "rollout" if kind == "deterministic" else "sampled rollout"
        for path in ("amx-network", "fma-network", "bmm"):
            for precision in ("fp32", "bf16"):
                if path not in base.world_model.engine.available_inference_paths(resolve_planning_dtype(precision) or torch.float32):
                    continue
                base.world_model.engine.inference_path = path
                with base._planning(precision), torch.no_grad():
                    base.set_seed(0)
                    fast = base._returns_by_rollout(kind, base._tensor_stack(tenv), obs, acts[:, :, 0], member)
                    compiled = [v.compiled is not None for k, v in base.world_model.engine._inference_cache.items()
                                if k[0] == cache_kind and path in (k[-4] or ())]  # k[-4]: the kernel paths
                    assert path == "bmm" or (compiled and all(compiled))
                    base.set_seed(0)
                    slow = base._returns_through_step(tenv, obs, acts, member)
                base.world_model.engine.inference_path = "auto"
                torch.testing.assert_close(fast, slow)
    scaled = TransformedEnv(_model_env("mean"), Compose(UncertaintyReward(), RewardScaling(0.0, 2.0)))
    assert scaled.base_env._tensor_stack(scaled) is None
    obs_td = TensorDict({"observation": torch.randn(2, 3)}, [2])
    acts = torch.rand(2, 4, 3, 2) * 2 - 1
    torch.testing.assert_close(scaled.base_env.evaluate_action_sequences(obs_td, acts, num_particles=1, env=scaled),
                               rollout_returns(scaled, obs_td, acts))


def test_candidates_are_the_clipped_samples_and_extras():
    """``sample_candidates`` (one buffer, one pass each for the samples and the clipping) gives the
    same values as adding, concatenating and clipping apart, the extras clipped too."""
    planner = ICEMPlanner(TransformedEnv(_model_env("mean"), UncertaintyReward()), planning_horizon=4)
    g = torch.Generator().manual_seed(0)
    mean, std = torch.randn(3, 1, 4, 2, generator=g), torch.rand(3, 1, 4, 2, generator=g)
    noise = torch.randn(3, 5, 2, 4, generator=g).transpose(-1, -2)  # strided, as colored noise comes
    extra = (3 * torch.randn(3, 2, 4, 2, generator=g), mean)
    got = planner.sample_candidates(mean, std, noise, extra)
    want = torch.cat([mean + std * noise, *extra], 1).clamp(-1, 1)
    assert got.shape == (3, 8, 4, 2) and torch.equal(got, want)
    assert got.abs().max() == 1.0  # some were clipped
