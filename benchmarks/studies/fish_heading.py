"""Why SoftAE's fish model, the most accurate on the held-out gaits, fails the forward task (iii)
that Random's model solves: where each method's explored data lies in heading, how accurate its
model is by heading, and what the model predicts along the forward episodes its own planner drives.

    python benchmarks/studies/fish_heading.py RUN [RUN ...]      # finished run dirs of SoftFish-v0
    python benchmarks/studies/fish_heading.py --table             # the committed results

The fish's state holds its velocity in the world frame and its heading ``yaw`` (0 at every
reset; the forward task rewards world ``v_x``, so solving it means staying near ``yaw = 0``).
Per run:

- ``data``: the share of explored transitions with ``|yaw| < 0.5`` rad, the median ``|yaw|``,
  and the share swimming faster than 0.2 m/s along the heading;
- ``heldout``: the held-out metric (normalized MSE of the ensemble mean, the run's own reference
  scale) on the held-out transitions by heading, ``|yaw| < 0.5``, ``0.5-1.5``, ``> 1.5``, beside
  ``s' = s`` on the same transitions;
- ``forward``: one forward episode of the zero-shot controller the replication evaluates (iCEM of
  the run's planner, mean propagation, H = 10; the first evaluation episode's seed), with the
  return, the model's one-step predicted ``v_x`` along the executed transitions against the real
  one (mean over the episode), the one-step normalized MSE on those transitions and the final
  ``|yaw|``.
Results: ``benchmarks/results/fish_heading/RUN.json``.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

RESULTS = Path(__file__).parents[1] / "results" / "fish_heading"
#: heading bins of the held-out split, rad
HEADING_BINS = {"|yaw| < 0.5": (0.0, 0.5), "0.5 <= |yaw| < 1.5": (0.5, 1.5), "|yaw| >= 1.5": (1.5, float("inf"))}
VX, YAW = 0, 3  # state layout of SoftFish-v0 (torchrl_softae.envs.robots.fish.fish_layout)


def _heading_speed(obs: torch.Tensor) -> torch.Tensor:
    return obs[:, VX] * torch.cos(obs[:, YAW]) + obs[:, VX + 1] * torch.sin(obs[:, YAW])


@torch.no_grad()
def study(run_dir: str, horizon: int = 10) -> dict:
    from torchrl_softae.pipeline.catalog import get_env_entry, get_task
    from torchrl_softae.pipeline.data import ModelAccuracy, normalized_mse, trivial_nmse
    from torchrl_softae.pipeline.evaluate import load_run, task_policy, task_rollouts
    from torchrl_softae.pipeline.policy import stored_transitions
    from torchrl_softae.pipeline.runs import RunDir

    cfg, model, state = load_run(run_dir)
    if cfg.env != "SoftFish-v0":
        raise SystemExit(f"{run_dir}: env {cfg.env!r}, expected SoftFish-v0")
    run = RunDir(run_dir)
    entry = get_env_entry(cfg.env)
    data = stored_transitions(run, state)["observation"]
    accuracy = ModelAccuracy(entry, run, cfg.heldout_size)
    held, scale = accuracy.heldout, accuracy.scale
    heading = held["observation"][:, YAW].abs()
    heldout = {}
    for name, (lo, hi) in HEADING_BINS.items():
        part = held[(heading >= lo) & (heading < hi)]
        heldout[name] = {"n": len(part), "model": normalized_mse(model, part, None, scale) if len(part) else None,
                         "identity": trivial_nmse(part, scale)["identity"] if len(part) else None}

    cfg.planner.horizon = horizon
    # the first evaluation episode of the replication records (evaluation seed 0)
    rollout = task_rollouts(cfg.env, get_task(entry, "forward"), 1, 0, keep_trajectories=True,
                            policy_for=lambda real, s, t: task_policy(cfg, model, t, real.action_spec, "mean", seed=s))
    traj = rollout["trajectories"][0]
    predicted = model.predict(traj["observation"], traj["action"])[0]
    forward = {"return": float(traj["next", "reward"].sum()),
               "predicted_vx": float(predicted[:, VX].mean()),
               "real_vx": float(traj["next", "observation"][:, VX].mean()),
               "one_step_nmse": normalized_mse(model, traj, None, scale),
               "final_abs_yaw": float(traj["next", "observation"][-1, YAW].abs())}
    return {"run": Path(run_dir).name, "env": cfg.env, "method": cfg.method, "seed": cfg.seed,
            "episodes": state["episode"] + 1, "transitions": len(data), "horizon": horizon,
            "data": {"share_abs_yaw_below_0.5": float((data[:, YAW].abs() < 0.5).float().mean()),
                     "median_abs_yaw": float(data[:, YAW].abs().median()),
                     "share_heading_speed_above_0.2": float((_heading_speed(data) > 0.2).float().mean())},
            "heldout": heldout, "forward": forward}


def table() -> str:
    import numpy as np

    results = [json.loads(p.read_text()) for p in sorted(RESULTS.glob("*.json"))]

    def cell(rs, get, fmt="{:.3f}"):
        v = np.array([get(r) for r in rs])
        return (fmt + " ± " + fmt).format(v.mean(), v.std(ddof=1)) if len(v) > 1 else fmt.format(v[0])

    bins = list(HEADING_BINS)
    lines = ["| method | n | explored with abs(yaw) < 0.5 | median abs(yaw), rad | "
             + " | ".join(f"held-out nMSE, {b.replace('|yaw|', 'abs(yaw)')}" for b in bins)
             + " | forward return | forward: predicted / real mean v_x, m/s | forward: one-step nMSE |",
             "|---|---|---|---|" + "---|" * len(bins) + "---|---|---|"]
    for method in dict.fromkeys(r["method"] for r in results):
        rs = [r for r in results if r["method"] == method]
        lines.append(
            f"| {method} | {len(rs)} | {cell(rs, lambda r: r['data']['share_abs_yaw_below_0.5'], '{:.2f}')} | "
            f"{cell(rs, lambda r: r['data']['median_abs_yaw'], '{:.2f}')} | "
            + " | ".join(cell(rs, lambda r, b=b: r["heldout"][b]["model"]) for b in bins)
            + f" | {cell(rs, lambda r: r['forward']['return'], '{:.1f}')} | "
            f"{cell(rs, lambda r: r['forward']['predicted_vx'])} / {cell(rs, lambda r: r['forward']['real_vx'])} | "
            f"{cell(rs, lambda r: r['forward']['one_step_nmse'])} |")
    identity = " | ".join(f"{results[0]['heldout'][b]['identity']:.3f}" for b in bins)
    lines.append(f"| *s' = s* | - | - | - | {identity} | - | - | - |")
    return "\n".join(lines)


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("runs", nargs="*", help="finished run dirs of SoftFish-v0")
    p.add_argument("--table", action="store_true", help="print the table of the committed results and exit")
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args()
    if args.table:
        print(table())
        return
    if not args.runs:
        p.error("name the finished run dirs to study (or --table)")
    torch.set_num_threads(args.threads)
    RESULTS.mkdir(parents=True, exist_ok=True)
    for run_dir in args.runs:
        result = study(run_dir)
        (RESULTS / f"{result['run']}-ep{result['episodes']}.json").write_text(json.dumps(result, indent=1))
        f = result["forward"]
        print(f"{result['run']}: explored |yaw| < 0.5 {result['data']['share_abs_yaw_below_0.5']:.2f}; held-out "
              + ", ".join(f"{b} {v['model']:.3f}" for b, v in result["heldout"].items())
              + f"; forward return {f['return']:.1f}, v_x predicted {f['predicted_vx']:+.3f} real {f['real_vx']:+.3f}",
              flush=True)


if __name__ == "__main__":
    main()
