"""EnsembleTrainer: the fit's fast path, mixed precision and the precision's resolution."""
import json
import math

import pytest
import torch
from tensordict import TensorDict

from torchrl_softae.modules import EnsembleWorldModel
from torchrl_softae.objectives import EnsembleLoss, EnsembleTrainer
from torchrl_softae.objectives.training import TRAINING_PRECISIONS, resolve_training_dtype, transitions_from


def _data(n=300, d_s=4, d_a=2, seed=0):
    g = torch.Generator().manual_seed(seed)
    obs = torch.randn(n, d_s, generator=g)
    act = torch.rand(n, d_a, generator=g) * 2 - 1
    nxt = obs + 0.1 * torch.tanh(obs) + 0.05 * act.sum(-1, keepdim=True)
    return TensorDict({"observation": obs, "action": act, ("next", "observation"): nxt}, [n])


def _model(seed=1, d_s=4, d_a=2):
    torch.manual_seed(seed)
    return EnsembleWorldModel(d_s, d_a, num_cells=32, depth=2)


def _params(model):
    return torch.cat([p.detach().flatten() for p in model.parameters()])


def _reference_fit(trainer: EnsembleTrainer, data, generator):
    """The fit as the loss module's tensordict path computes it: every minibatch indexed from the
    tensordict, normalized and checked on its own (what ``fit`` did before it gathered rows from
    inputs and targets normalized once)."""
    loss_module, model = trainer.loss_module, trainer.model
    keys = [loss_module.tensor_keys.observation, loss_module.tensor_keys.action, loss_module.tensor_keys.next_observation]
    td = transitions_from(data, keys)
    n = td.shape[0]
    perm = torch.randperm(n, generator=generator)
    n_val = int(round(trainer.val_fraction * n))
    train = td[perm[n_val:]]
    model.fit_normalizers(*(train.get(k) for k in keys))
    L, bs = model.ensemble_size, trainer.batch_size
    steps_per_epoch = math.ceil(train.shape[0] / bs)
    total = min(trainer.epochs * steps_per_epoch, trainer.max_grad_steps)
    step = 0
    model.train()
    while step < total:
        order = torch.rand(L, train.shape[0], generator=generator).argsort(dim=1)
        for j in range(min(steps_per_epoch, total - step)):
            idx = order[:, j * bs:(j + 1) * bs]
            loss = loss_module(train[idx.reshape(-1)].reshape(L, idx.shape[1]))["loss_model"]
            trainer.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            trainer.optimizer.step()
        step += min(steps_per_epoch, total - step)
    model.eval()


def test_fit_trains_exactly_as_the_loss_modules_tensordict_path():
    data = _data()
    fast = EnsembleTrainer(EnsembleLoss(_model()), lr=1e-3, epochs=3, batch_size=32, max_grad_steps=20)
    slow = EnsembleTrainer(EnsembleLoss(_model()), lr=1e-3, epochs=3, batch_size=32, max_grad_steps=20)
    report = fast.fit(data, generator=torch.Generator().manual_seed(7))
    _reference_fit(slow, data, torch.Generator().manual_seed(7))
    assert report.grad_steps == 20 and report.precision == "fp32"
    assert torch.equal(_params(fast.model), _params(slow.model))  # bit for bit, fp32


def test_bf16_training_runs_bf16_matmuls_on_fp32_weights_and_learns_as_fp32_does():
    data = _data(600)
    trainers = {p: EnsembleTrainer(EnsembleLoss(_model()), lr=3e-3, epochs=20, precision=p) for p in ("fp32", "bf16")}
    reports = {p: t.fit(data) for p, t in trainers.items()}
    bf16 = trainers["bf16"]
    assert reports["bf16"].precision == "bf16" and bf16.dtype == torch.bfloat16
    assert all(p.dtype == torch.float32 for p in bf16.model.parameters())
    assert all(v.dtype == torch.float32 for s in bf16.optimizer.state.values() for k, v in s.items() if k != "step")
    # the matmuls did run in bf16: the weights moved differently from fp32's ...
    assert not torch.equal(_params(bf16.model), _params(trainers["fp32"].model))
    # ... and learned as much: validation error fell as far (within 10 %) in both
    first, last = reports["fp32"].val_mse[0], reports["fp32"].val_mse[-1]
    assert last < 0.1 * first
    assert reports["bf16"].val_mse[-1] == pytest.approx(last, rel=0.1)


def test_the_loss_under_bf16_autocast_is_fp32_and_close_to_fp32s():
    model = _model()
    model.fit_normalizers(*(_data()[k] for k in ("observation", "action", ("next", "observation"))))
    loss_module = EnsembleLoss(model)
    x, y = torch.randn(5, 16, 6), torch.randn(5, 16, 4)
    ref, _ = loss_module.normalized_loss(x, y)  # with autograd on: the training path
    with torch.autocast("cpu", dtype=torch.bfloat16):
        low, mse = loss_module.normalized_loss(x, y)
    assert low.dtype == torch.float32 and mse.dtype == torch.float32
    low, ref = float(low.detach()), float(ref.detach())
    assert low != ref and low == pytest.approx(ref, rel=2e-2)


def test_auto_is_fp32_without_native_bf16_and_a_measured_choice_with_it(tmp_path, monkeypatch):
    from torchrl_softae.modules.engine import paths, precision

    monkeypatch.setenv("TORCHRL_SOFTAE_CACHE", str(tmp_path))
    monkeypatch.setattr(paths, "_MEMORY", {})
    model = _model()
    monkeypatch.setattr(precision, "fast_bf16_available", lambda: False)
    assert resolve_training_dtype("auto", model) == torch.float32
    assert not (tmp_path / "paths.json").exists()  # nothing timed
    monkeypatch.setattr(precision, "fast_bf16_available", lambda: True)
    before = [p.detach().clone() for p in model.parameters()]
    chosen = resolve_training_dtype("auto", model)
    assert chosen in (torch.float32, torch.bfloat16)
    assert all(torch.equal(a, b) for a, b in zip(before, model.parameters()))  # timed on another model
    (key, value), = json.loads((tmp_path / "paths.json").read_text()).items()
    assert "training step" in key and "batch 64" in key and value == ("bf16" if chosen == torch.bfloat16 else "fp32")
    monkeypatch.setattr(paths, "_MEMORY", {})  # another process reads the choice from disk
    assert resolve_training_dtype("auto", model) == chosen
    assert resolve_training_dtype("fp32", model) == torch.float32
    assert resolve_training_dtype("bf16", model) == torch.bfloat16


def test_the_resolved_precision_is_kept_in_the_trainers_state():
    trainer = EnsembleTrainer(EnsembleLoss(_model()), precision="bf16", epochs=1)
    trainer.fit(_data())
    state = trainer.state_dict()
    assert state["precision"] == "bf16"
    resumed = EnsembleTrainer(EnsembleLoss(_model()), precision="auto")
    resumed.load_state_dict(state)
    assert resumed.dtype == torch.bfloat16  # as the run began, whatever auto would pick now
    old = {"optimizer": state["optimizer"]}  # a checkpoint from before the choice existed: fp32
    resumed = EnsembleTrainer(EnsembleLoss(_model()), precision="auto")
    resumed.load_state_dict(old)
    assert resumed.dtype == torch.float32
    with pytest.raises(ValueError, match="precision='fp32', but the checkpoint trained in bf16"):
        EnsembleTrainer(EnsembleLoss(_model()), precision="fp32").load_state_dict(state)


def test_bad_precision_is_one_clear_error():
    with pytest.raises(ValueError, match="precision='fp16', expected one of auto, fp32, bf16"):
        EnsembleTrainer(EnsembleLoss(_model()), precision="fp16")
    from torchrl_softae.pipeline.config import ConfigError, make_config

    with pytest.raises(ConfigError, match="train.precision='fp16'; valid: auto, fp32, bf16"):
        make_config("Pendulum-v1", "softae", ["train.precision=fp16"])
    assert make_config("Pendulum-v1", "softae").train.precision == "auto" and "auto" in TRAINING_PRECISIONS


def test_float64_data_trains_a_float32_model_and_float64_inputs_get_one_clear_error():
    data = _data().to(torch.float64)  # what gymnasium's MuJoCo envs give
    trainer = EnsembleTrainer(EnsembleLoss(_model()), lr=1e-3, epochs=2)
    report = trainer.fit(data)
    assert report.grad_steps > 0 and all(p.dtype == torch.float32 for p in trainer.model.parameters())
    with pytest.raises(TypeError, match=r"'observation' is torch.float64, the model's parameters torch.float32: "
                                        r"cast the data \(TorchRL's DoubleToFloat"):
        trainer.model.predict(data["observation"], data["action"])
    with pytest.raises(TypeError, match="DoubleToFloat"):
        EnsembleLoss(trainer.model)(data[:8])


def test_trainer_drops_non_finite_transitions_and_reads_replay_buffers():
    from torchrl.data import LazyTensorStorage, ReplayBuffer

    m = EnsembleWorldModel(3, 2, num_cells=32, depth=2)
    rb = ReplayBuffer(storage=LazyTensorStorage(100))
    td = TensorDict(
        {"observation": torch.randn(40, 3), "action": torch.randn(40, 2), ("next", "observation"): torch.randn(40, 3)}, [40]
    )
    td["next", "observation"][3] = float("nan")
    rb.extend(td)
    report = EnsembleTrainer(EnsembleLoss(m), epochs=2, lr=1e-3).fit(rb)
    assert report.num_train + report.num_val == 39
    assert report.grad_steps == 2 * 1  # 35 train rows, batch 64 -> one step per epoch
    assert all(torch.isfinite(torch.tensor(report.train_loss)))


def test_trainer_uses_fused_adam_on_cpu_with_the_same_updates():
    torch.manual_seed(0)
    obs = torch.randn(200, 3)
    td = TensorDict({"observation": obs, "action": torch.randn(200, 2), ("next", "observation"): obs.sin()}, [200])
    params = {}
    for fused in (None, False):
        torch.manual_seed(1)
        trainer = EnsembleTrainer(EnsembleLoss(EnsembleWorldModel(3, 2, num_cells=32, depth=2)), lr=1e-3, epochs=3, fused=fused)
        assert trainer.fused is (fused is None)
        report = trainer.fit(td)
        params[fused] = torch.cat([p.detach().flatten() for p in trainer.model.parameters()])
        assert report.val_mse[-1] < report.val_mse[0]
    torch.testing.assert_close(params[None], params[False], rtol=1e-4, atol=1e-5)
