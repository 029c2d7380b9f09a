"""The one switch between the compiled kernels and pure torch: ``kernels="torch"`` where a model is
built, ``SOFTAE_KERNELS=0`` for the whole process (as an install without a C compiler)."""
import os
import subprocess
import sys

import pytest
import torch
from torchrl.data import Bounded

from torchrl_softae.envs import EnsembleModelEnv
from torchrl_softae.modules import EnsembleWorldModel

TORCH_PATHS = {"conv", "conv-fused", "bmm"}


def _pair():
    torch.manual_seed(0)
    auto = EnsembleWorldModel(6, 2, ensemble_size=3, num_cells=32, depth=2)
    plain = EnsembleWorldModel(6, 2, ensemble_size=3, num_cells=32, depth=2, kernels="torch")
    plain.load_state_dict(auto.state_dict())
    x = torch.randn(400, 6)
    a = torch.rand(400, 2) * 2 - 1
    auto.fit_normalizers(x, a, x + 0.1 * torch.randn_like(x))
    plain.load_state_dict(auto.state_dict())
    return auto.eval(), plain.eval(), x, a


def test_a_torch_model_runs_torch_paths_only_and_predicts_what_the_kernels_do():
    auto, plain, x, a = _pair()
    assert not plain.engine.uses_kernels and set(plain.engine.available_inference_paths()) <= TORCH_PATHS
    with torch.no_grad():
        for p, q in zip(auto.predict(x, a), plain.predict(x, a)):
            if p is not None:
                torch.testing.assert_close(p, q, rtol=1e-5, atol=1e-5)
        for p, q in zip(auto.predict_moments(x, a), plain.predict_moments(x, a)):
            if p is not None:
                torch.testing.assert_close(p, q, rtol=1e-5, atol=1e-5)


def test_a_torch_model_env_draws_its_noise_by_torch_randn():
    _, plain, x, a = _pair()
    env = EnsembleModelEnv(plain, action_spec=Bounded(-1.0, 1.0, (2,)), mode="sample")
    env.set_seed(3)
    state = env._generator.get_state()
    with torch.no_grad():
        nxt, _ = env.propagate(x[:5], a[:5])
        env._generator.set_state(state)
        member = torch.randint(plain.ensemble_size, (5,), generator=env._generator)
        mu, sigma, member_mean, ale = plain.predict_moments(x[:5], a[:5], with_aleatoric=True, member_index=member)
        expected = member_mean + ale * torch.randn(member_mean.shape, generator=env._generator)
    torch.testing.assert_close(nxt, expected)


def test_a_bad_kernels_choice_is_one_clear_error():
    with pytest.raises(ValueError, match="kernels='c': expected one of auto, torch"):
        EnsembleWorldModel(6, 2, kernels="c")
    from torchrl_softae.pipeline.config import ConfigError, make_config

    assert make_config("Pendulum-v1", "softae", ["model.kernels=torch"]).model.kernels == "torch"
    with pytest.raises(ConfigError, match="model.kernels='c'; valid: auto, torch"):
        make_config("Pendulum-v1", "softae", ["model.kernels=c"])


def test_softae_kernels_0_unloads_every_kernel_in_the_process():
    code = ("from torchrl_softae.modules.engine import amx_network, fma_network, moments_kernel, normal_kernel, silu_kernel\n"
            "from torchrl_softae.modules import EnsembleWorldModel\n"
            "m = EnsembleWorldModel(6, 2)\n"
            "print([k.available() for k in (amx_network, fma_network, moments_kernel, normal_kernel, silu_kernel)],"
            " m.engine.uses_kernels, sorted(m.engine.available_inference_paths()))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={**os.environ, "SOFTAE_KERNELS": "0"}).stdout.strip()
    assert out == "[False, False, False, False, False] False ['bmm', 'conv', 'conv-fused']", out
