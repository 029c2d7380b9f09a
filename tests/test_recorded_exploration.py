"""A recorded short exploration reproduces its history exactly, with the kernels on: the guard that
moving or reworking the inference engine changes no result. One case per propagation (SoftAE with
bf16 planning, PETS-AE with particles and noise, Mean-AE), each on the fastest kind of inference
path this CPU runs (fixed, not measured: a measured choice may differ between runs), recorded per
CPU kind and torch version (other CPUs round differently): ``SOFTAE_RECORD=1 python -m pytest
tests/test_recorded_exploration.py`` records this machine's."""
import json
import os
from pathlib import Path

import pytest
import torch

from torchrl_softae.modules import InferenceEngine
from torchrl_softae.modules.engine import kernels, silu_kernel
from torchrl_softae.modules.engine.paths import cpu_key
from torchrl_softae.modules.engine.precision import cpu_info
from torchrl_softae.pipeline.cli import main
from torchrl_softae.pipeline.runs import RunDir

RECORDS = Path(__file__).parent / "recorded" / "explorations.json"
TINY = ["--env", "Pendulum-v1", "--episodes", "2", "--episode-length", "30", "--seed", "0", "--wandb", "disabled",
        "--quiet", "--threads", "1", "--set", "heldout_size=200", "--set", "model.num_cells=64", "--set",
        "model.depth=2", "--set", "planner.num_candidates=20", "--set", "planner.top_k=4", "--set",
        "planner.optim_steps=2", "--set", "train.epochs=3"]
#: case -> (arguments, planning dtype, the inference paths to prefer: the first that runs here in
#: fp32 (the held-out metric's calls) and in the planning dtype)
CASES = {
    "softae-bf16": (["--method", "softae", "--set", "planner.precision=bf16"], torch.bfloat16,
                    ("fma-network", "bmm-silu-kernel", "bmm")),
    "pets-ae-particles": (["--method", "pets-ae", "--set", "planner.num_particles=3"], torch.float32,
                          ("fma-network", "bmm-silu-kernel", "bmm")),
    "mean-ae": (["--method", "mean-ae"], torch.float32, ("conv-silu-kernel", "conv-fused", "bmm")),
}
TIMING = ("collect_seconds", "train_seconds", "cpu_seconds", "plan_ms_per_step")


def machine_key() -> str:
    return f"{cpu_key(cpu_info(), silu_kernel.cache_tag())}|torch {torch.__version__}"


@pytest.mark.skipif(not kernels.ENABLED, reason="the recorded histories ran with the kernels on")
@pytest.mark.parametrize("case", sorted(CASES))
def test_a_recorded_exploration_reproduces_its_history_exactly(case, tmp_path, monkeypatch):
    argv, dtype, preferred = CASES[case]
    from torchrl_softae.modules import EnsembleWorldModel

    engine = EnsembleWorldModel(3, 1, num_cells=8, depth=1).engine
    runs_here = set(engine.available_inference_paths(dtype)) & set(engine.available_inference_paths(torch.float32))
    path = next(p for p in preferred if p in runs_here)
    monkeypatch.setattr(InferenceEngine, "inference_path", path)
    assert main(["explore", *TINY, *argv, "--run-dir", str(tmp_path / case)]) == 0
    history = [{k: v for k, v in row.items() if k not in TIMING} for row in RunDir(tmp_path / case).history()]
    records = json.loads(RECORDS.read_text()) if RECORDS.exists() else {}
    if os.environ.get("SOFTAE_RECORD") == "1":
        records.setdefault(machine_key(), {})[case] = {"path": path, "history": history}
        RECORDS.parent.mkdir(exist_ok=True)
        RECORDS.write_text(json.dumps(records, indent=1, sort_keys=True) + "\n")
        pytest.skip(f"recorded {case} on {machine_key()}")
    recorded = records.get(machine_key(), {}).get(case)
    if recorded is None:
        pytest.skip(f"no recorded exploration for this CPU and torch ({machine_key()}): SOFTAE_RECORD=1 records one")
    assert recorded["path"] == path
    assert history == recorded["history"]
