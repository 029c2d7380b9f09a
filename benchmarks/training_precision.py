"""Does bf16 training (EnsembleTrainer(precision="bf16")) learn the arm's dynamics as well as fp32?

    python benchmarks/training_precision.py [--env SoftArm-v1] [--seeds 5] [--transitions 4000]
                                            [--threads 1] [--out benchmarks/results/training_precision/ENV.json]

Data: ``--transitions`` i.i.d. random-action transitions of the env (its catalog ``reference``
generator, the arm's, at seed 2024, disjoint from the held-out set's 12345 and the metric's
reference set's 54321) for training, and 1,000 more at seed 2025 for validation; built once and
cached beside the held-out set (``$TORCHRL_SOFTAE_CACHE``). Each seed trains the paper's ensemble
(Table S6: 5 x 4 x 256, lr 5e-5, batch 64, 50 epochs, at most 5,000 gradient steps, fused Adam) once
in fp32 and once in bf16 from the same initial weights and minibatch order, and is scored on:
  val_nll      Gaussian NLL per member on the validation set (``(mu - y)^2 e^-logvar + logvar``,
               normalized units, mean over members, rows and dimensions)
  val_mse      the trainer's validation MSE of the ensemble mean (normalized units)
  heldout_nmse the pipeline's held-out metric (``softae explore``'s ``heldout_nmse``), overall and by group
and the wall-clock of the fit. The table gives mean +- sample std (ddof = 1) and n per precision,
and whether the bf16 mean lies within the fp32 mean +- the fp32 seed-to-seed std.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parent))
from planning_speed import cpu_description  # noqa: E402

from torchrl_softae import keep_freed_memory  # noqa: E402
from torchrl_softae.modules import EnsembleWorldModel  # noqa: E402
from torchrl_softae.objectives import EnsembleLoss, EnsembleTrainer  # noqa: E402
from torchrl_softae.pipeline.catalog import get_env_entry  # noqa: E402
from torchrl_softae.pipeline.config import make_config  # noqa: E402
from torchrl_softae.pipeline.data import ModelAccuracy, _cached  # noqa: E402

PRECISIONS = ("fp32", "bf16")
TRAIN_SEED, VAL_SEED, VAL_SIZE = 2024, 2025, 1000


def summary(values: list[float]) -> dict:
    return {"mean": statistics.mean(values), "std": statistics.stdev(values) if len(values) > 1 else float("nan"),
            "n": len(values)}


@torch.no_grad()
def validation_nll(model: EnsembleWorldModel, td) -> float:
    obs, act, nxt = td["observation"], td["action"], td["next", "observation"]
    mean, logvar = model.network(model.network_input(obs, act))
    target = model.normalized_target(obs, nxt)
    return float(((mean - target).square() * torch.exp(-logvar) + logvar).mean())


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--env", default="SoftArm-v1")
    p.add_argument("--seeds", type=int, default=5)
    p.add_argument("--transitions", type=int, default=4000)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", default=None)
    args = p.parse_args()
    if args.seeds < 3:
        p.error(f"--seeds {args.seeds}: expected at least 3 (a spread needs them)")
    if args.transitions < 100:
        p.error(f"--transitions {args.transitions}: expected at least 100")
    torch.set_num_threads(args.threads)
    keep_freed_memory()
    entry = get_env_entry(args.env)
    if entry.reference is None:
        p.error(f"--env {args.env}: expected an env with a random-action generator (its catalog 'reference')")
    cfg = make_config(args.env, "softae")
    say = lambda line: print(line, flush=True)  # noqa: E731
    accuracy = ModelAccuracy(entry, None, cfg.heldout_size, announce=say)
    train = _cached(entry, "precision-train", entry.reference, args.transitions, TRAIN_SEED, None, say)
    val = _cached(entry, "precision-val", entry.reference, VAL_SIZE, VAL_SEED, None, say)
    d_s, d_a = train["observation"].shape[-1], train["action"].shape[-1]
    print(f"CPU: {cpu_description()}; torch {torch.__version__}, {args.threads} thread(s); {args.env}: "
          f"{train.shape[0]} training and {val.shape[0]} validation transitions, held-out {accuracy.heldout.shape[0]}")
    rows = []
    for seed in range(args.seeds):
        for precision in PRECISIONS:
            torch.manual_seed(seed)
            model = EnsembleWorldModel(d_s, d_a, ensemble_size=cfg.model.ensemble_size, num_cells=cfg.model.num_cells,
                                       depth=cfg.model.depth)
            t = cfg.train
            trainer = EnsembleTrainer(EnsembleLoss(model), lr=t.lr, batch_size=t.batch_size, epochs=t.epochs,
                                      max_grad_steps=t.max_grad_steps, val_fraction=t.val_fraction, precision=precision)
            t0 = time.perf_counter()
            report = trainer.fit(train, generator=torch.Generator().manual_seed(seed))
            seconds = time.perf_counter() - t0
            row = {"seed": seed, "precision": report.precision, "fit_seconds": seconds, "grad_steps": report.grad_steps,
                   "val_nll": validation_nll(model, val), "val_mse": trainer.validation_mse(val), **accuracy(model)}
            rows.append(row)
            print(f"seed {seed} {precision}: val NLL {row['val_nll']:.4f}, val MSE {row['val_mse']:.4f}, held-out "
                  f"nMSE {row['heldout_nmse']:.4f}, {report.grad_steps} steps in {seconds:.1f} s", flush=True)
    metrics = [k for k in rows[0] if k in ("val_nll", "val_mse", "fit_seconds") or k.startswith("heldout_nmse")]
    table = {}
    print(f"\n| metric | fp32 | bf16 | bf16 within fp32 mean +- std |\n|---|---|---|---|")
    for metric in metrics:
        s = {prec: summary([r[metric] for r in rows if r["precision"] == prec]) for prec in PRECISIONS}
        within = abs(s["bf16"]["mean"] - s["fp32"]["mean"]) <= s["fp32"]["std"]
        table[metric] = {**s, "bf16_within_fp32_spread": within}
        print(f"| {metric} | {s['fp32']['mean']:.4g} +- {s['fp32']['std']:.2g} (n={s['fp32']['n']}) | "
              f"{s['bf16']['mean']:.4g} +- {s['bf16']['std']:.2g} (n={s['bf16']['n']}) | "
              f"{'yes' if within else 'no'} |")
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps({
            "env": args.env, "cpu": cpu_description(), "torch": torch.__version__, "threads": args.threads,
            "transitions": train.shape[0], "validation": val.shape[0], "heldout": accuracy.heldout.shape[0],
            "train": {"lr": cfg.train.lr, "batch_size": cfg.train.batch_size, "epochs": cfg.train.epochs,
                      "max_grad_steps": cfg.train.max_grad_steps},
            "baselines": accuracy.baselines, "rows": rows, "table": table}, indent=1))


if __name__ == "__main__":
    main()
