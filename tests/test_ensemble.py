"""The ensemble world model's maths: shapes, members, mu and sigma, normalizers, log-variance
bounds, symlog, and bad input."""
import warnings

import pytest
import torch
from tensordict import TensorDict

from torchrl_softae.modules import EnsembleWorldModel, ensemble_std
from torchrl_softae.objectives import EnsembleLoss, EnsembleTrainer


def _model(**kw):
    kw = {"num_cells": 32, "depth": 2, **kw}
    return EnsembleWorldModel(3, 2, **kw)


def test_forward_shapes_and_keys():
    m = _model()
    td = TensorDict({"observation": torch.randn(4, 7, 3), "action": torch.randn(4, 7, 2)}, [4, 7])
    out = m(td)
    for k in ("loc", "epistemic_std", "aleatoric_std"):
        assert out[k].shape == (4, 7, 3)
    assert (out["epistemic_std"] >= 0).all() and (out["aleatoric_std"] > 0).all()
    members, ale = m.predict_members(td["observation"], td["action"])
    assert members.shape == (5, 4, 7, 3) and ale.shape == (5, 4, 7, 3)
    torch.testing.assert_close(members.mean(0), out["loc"])
    torch.testing.assert_close(members.std(0), out["epistemic_std"])


def test_members_are_one_batched_computation_matching_independent_mlps():
    m = _model()
    for layer in m.layers:
        assert layer.weight.shape[0] == 5  # stacked (L, in, out)
    obs, act = torch.randn(6, 3), torch.randn(6, 2)
    members, _ = m.predict_members(obs, act)
    x = m.input_normalizer.normalize(torch.cat([obs, act], -1))
    for l in range(5):  # reference: member l as a plain MLP
        h = x
        for i, layer in enumerate(m.layers):
            h = h @ layer.weight[l] + layer.bias[l, 0]
            if i < len(m.layers) - 1:
                h = torch.nn.functional.silu(h)
        ref = obs + m.output_normalizer.denormalize(h[:, :3])
        torch.testing.assert_close(members[l], ref)
    # both inference paths (no autograd, cached weights) agree with it: grouped 1x1 convolutions
    # (oneDNN, CPU) and batched matmuls in thread-balanced row chunks, with and without the
    # log-variance head, on shared and on per-member inputs
    with torch.no_grad():
        torch.testing.assert_close(m.predict_members(obs.repeat(4, 1), act.repeat(4, 1))[0][:, :6], members)
        xs = x.repeat(4, 1)
        silu = torch.nn.functional.silu
        ref_y = m.layers[2](silu(m.layers[1](silu(m.layers[0](xs.expand(5, -1, -1))))))  # (L, N, 2 d_s)
        assert torch.backends.mkldnn.is_available()  # the CPU build ships oneDNN: the conv path is tested
        for cols in (None, 3):
            want = ref_y if cols is None else ref_y[..., :cols]
            torch.testing.assert_close(m.engine._network_grouped_conv(xs, torch.float32, cols), want)
            torch.testing.assert_close(m.engine._network_bmm(xs, torch.float32, cols), want)
        torch.testing.assert_close(m.engine._network_bmm(xs.expand(5, -1, -1), torch.float32, None), ref_y)
        with warnings.catch_warnings():  # flags() warns about Intel-GPU TF32, irrelevant here
            warnings.simplefilter("ignore")
            with torch.backends.mkldnn.flags(enabled=False):  # falls back to the matmul path
                torch.testing.assert_close(m.predict_members(obs, act)[0], members)
    # members differ (independent initialization)
    assert (members[0] - members[1]).abs().max() > 1e-3


def test_ensemble_std_matches_torch_std():
    x = torch.randn(5, 100, 7)
    torch.testing.assert_close(ensemble_std(x), x.std(0))


def _regression_data(n=256):
    x = torch.rand(n, 1) * 2 - 1  # data only on [-1, 1]
    return TensorDict(
        {"observation": x, "action": torch.zeros(n, 1), ("next", "observation"): torch.sin(3 * x)}, [n]
    )


def test_sigma_shrinks_where_data_lies_and_loss_decreases():
    m = EnsembleWorldModel(1, 1, num_cells=64, depth=2)
    trainer = EnsembleTrainer(EnsembleLoss(m), lr=3e-3, epochs=150, max_grad_steps=10_000, batch_size=32)
    data = _regression_data()
    report = trainer.fit(data, generator=torch.Generator().manual_seed(0))
    assert report.train_loss[-1] < report.train_loss[0] - 1.0
    assert report.val_mse[-1] < 0.05 * report.val_mse[0] or report.val_mse[-1] < 0.01
    x_in = torch.linspace(-0.9, 0.9, 50)[:, None]
    x_out = torch.cat([torch.linspace(-6, -4, 25), torch.linspace(4, 6, 25)])[:, None]
    _, s_in, _, _ = m.predict(x_in, torch.zeros(50, 1))
    _, s_out, _, _ = m.predict(x_out, torch.zeros(50, 1))
    assert s_out.mean() > 5 * s_in.mean(), (s_in.mean(), s_out.mean())
    mu, *_ = m.predict(x_in, torch.zeros(50, 1))
    assert (mu - torch.sin(3 * x_in)).abs().mean() < 0.1


def test_squared_error_option_and_per_member_minibatches_get_own_gradients():
    m = _model(probabilistic=False)
    loss = EnsembleLoss(m)
    assert loss.loss_type == "mse"
    td = TensorDict(
        {"observation": torch.randn(5, 16, 3), "action": torch.randn(5, 16, 2), ("next", "observation"): torch.randn(5, 16, 3)},
        [5, 16],
    )
    out = loss(td)
    out["loss_model"].backward()
    g = m.layers[0].weight.grad
    assert g is not None and (g.flatten(1).norm(dim=1) > 0).all()
    # member 0's gradient only depends on member 0's minibatch
    m.zero_grad()
    td2 = td.clone()
    td2["observation"][1:] += 1.0
    loss(td2)["loss_model"].backward()
    g2 = m.layers[0].weight.grad
    torch.testing.assert_close(g[0], g2[0])
    assert not torch.allclose(g[1], g2[1])


def test_normalizers_saved_with_model():
    m = _model()
    obs, act = torch.randn(100, 3) * 5 + 2, torch.randn(100, 2)
    m.fit_normalizers(obs, act, obs + 0.1 * torch.randn(100, 3))
    m2 = _model()
    m2.load_state_dict(m.state_dict())
    torch.testing.assert_close(m2.input_normalizer.scale, m.input_normalizer.scale)
    torch.testing.assert_close(m2.predict(obs, act)[0], m.predict(obs, act)[0])


def test_logvar_soft_bounds():
    m = _model()
    x = torch.randn(5, 8, 5) * 1e4
    _, logvar = m.network(x)
    # soft bounds: within softplus' tail (exp(-(max - min)) ~ 3e-5) of the bounds
    assert (logvar <= m.max_logvar + 1e-4).all() and (logvar >= m.min_logvar - 1e-4).all()
    assert logvar.max() > 0.49 and logvar.min() < -9.99  # saturates at the bounds, no further


@pytest.mark.parametrize(
    "obs, act, match",
    [
        (torch.randn(4, 2), torch.randn(4, 2), "'observation' has shape"),
        (torch.randn(4, 3), torch.randn(4, 5), "'action' has shape"),
        (torch.tensor([[0.0, float("nan"), 1.0]]), torch.zeros(1, 2), "'observation' contains NaN"),
        (torch.zeros(1, 3), torch.tensor([[float("inf"), 0.0]]), "'action' contains NaN"),
        (torch.randn(4, 3), torch.randn(3, 2), "batch shapes differ"),
    ],
)
def test_bad_input_raises_naming_the_value(obs, act, match):
    with pytest.raises(ValueError, match=match):
        _model()(TensorDict({"observation": obs, "action": act}, []))


def test_bad_hyperparameters():
    with pytest.raises(ValueError, match="ensemble_size=1"):
        EnsembleWorldModel(3, 2, ensemble_size=1)
    with pytest.raises(ValueError, match="lr=-1"):
        EnsembleTrainer(EnsembleLoss(_model()), lr=-1)
    with pytest.raises(ValueError, match="loss_type='huber'"):
        EnsembleLoss(_model(), loss_type="huber")


def test_symlog_round_trip_and_a_symlog_model_predicts_in_original_units():
    from torchrl_softae.modules import symexp, symlog

    x = torch.tensor([-1e4, -3.0, -1e-3, 0.0, 2e-4, 5.0, 3e5])
    torch.testing.assert_close(symexp(symlog(x)), x, rtol=1e-5, atol=1e-6)
    # states spanning orders of magnitude: s' = 1.1 s + a
    s = torch.cat([torch.randn(600, 1) * 1000, torch.randn(600, 1) * 0.01], -1)
    a = torch.rand(600, 1) * 2 - 1
    td = TensorDict({"observation": s, "action": a, ("next", "observation"): 1.1 * s + a}, [600])
    model = EnsembleWorldModel(2, 1, num_cells=64, depth=2, symlog_observations=True)
    EnsembleTrainer(EnsembleLoss(model), lr=3e-3, epochs=60).fit(td)
    mu, sigma, ale, members = model.predict(s[:100], a[:100])
    assert members.shape == (5, 100, 2) and (ale > 0).all() and (sigma >= 0).all()
    rel = ((mu - (1.1 * s[:100] + a[:100])).abs() / (1.1 * s[:100] + a[:100]).abs().clamp_min(0.05)).median()
    assert rel < 0.2, rel  # predictions in original units, large and small dimensions alike
