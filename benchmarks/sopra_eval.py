"""SoPrA (simulated twin): explore with Random, H-UCRL and SoftAE, then reach 20 random targets and
track a square and a lemniscate zero-shot; the paper's real-arm numbers alongside.

    python benchmarks/sopra_eval.py                       # 3 methods x 3 seeds
    python benchmarks/sopra_eval.py --seeds 0 --episodes 1 --targets 3 --smoke

Exploration: EPISODES x 200 steps per method (``quick`` preset, iCEM H=5, colored-noise exponent
1.0 as in Table S7; H-UCRL is optimistic on the reach-close task reward). Evaluation: 20 targets
drawn uniformly from the twin's reachable workspace (settled tips under random pressures within
the 400 mbar cap), 20 steps each (task horizon of the paper), reward g(d) summed (max 20), final
tip error in mm. Tracking: a 30 mm square and a 40 x 20 mm lemniscate in the horizontal plane
through the rest tip, 80 steps each; the MPC's target moves to the next reference point every
step; error = horizontal distance. Each (method, seed) resumes its run dir and, when done, writes
benchmarks/results/sopra/METHOD-sSEED.json (rerunning skips it); the table (mean +- std over seeds)
goes to benchmarks/results/sopra_eval.md, the plots to benchmarks/results/plots/sopra_tracking_*.png.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from torchrl_softae.pipeline.cli import PRESETS
from torchrl_softae.pipeline.config import make_config
from torchrl_softae.envs.robots.sopra import SoPrAEnv
from torchrl_softae.tasks.sopra import sopra_reach_task
from torchrl_softae.pipeline.evaluate import load_run, task_policy
from torchrl_softae.pipeline.explore import explore

RESULTS = Path(__file__).parent / "results"
RUNS = RESULTS / "runs" / "sopra"  # run dirs (not committed); a smoke run's outputs stay here too
PAPER = {  # real SoPrA, the paper's table: mean return, mean / min / max tip error [mm]
    "softae": (17.78, 2.00, 0.49, 4.70), "random": (17.63, 3.82, 1.20, 9.57), "hucrl": (15.23, 10.15, 1.14, 49.41),
}


def rollout_to_target(cfg, model, env, target, steps, seed):
    task = sopra_reach_task("target", target, horizon=steps)
    policy = task_policy(cfg, model, task, env.action_spec, seed=seed)
    env.set_seed(seed)
    traj = env.rollout(steps, policy, break_when_any_done=True)
    reward = task.reward(traj["observation"], traj["action"], traj["next", "observation"])
    tips = traj["next", "observation"][:, :3].numpy()
    return float(reward.sum()), float(np.linalg.norm(tips[-1] - target)) * 1e3


def track(cfg, model, env, path, seed):
    """MPC whose target is the next reference point at every step (tensor updated in place)."""
    target = torch.as_tensor(path[0], dtype=torch.float32).clone()
    from torchrl_softae.envs.robots.reach import reach_reward
    from torchrl_softae.tasks.base import Task

    task = Task("track", lambda s, a, s2: reach_reward((s2[..., 0:3] - target).norm(dim=-1)), len(path))
    policy = task_policy(cfg, model, task, env.action_spec, seed=seed)
    env.set_seed(seed)
    td = env.reset()
    tips = []
    for k in range(len(path) - 1):
        target.copy_(torch.as_tensor(path[k + 1], dtype=torch.float32))
        td = policy(td)
        td = env.step(td)
        tips.append(td["next", "observation"][:3].numpy())
        td = td["next"]
        if bool(td["terminated"]):
            break
    tips = np.array(tips)
    err = np.linalg.norm(tips[:, :2] - path[1 : len(tips) + 1, :2], axis=1) * 1e3
    return tips, err


def reference_paths(rest_tip, n=80):
    t = np.linspace(0, 1, n)
    side = 0.03
    # square: four edges of equal duration, starting at a corner
    corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1], [-1, -1]]) * side / 2
    seg = np.minimum((t * 4).astype(int), 3)
    frac = t * 4 - seg
    sq = corners[seg] + (corners[seg + 1] - corners[seg]) * frac[:, None]
    th = 2 * np.pi * t
    lem = np.stack([0.02 * np.sin(th), 0.01 * np.sin(2 * th)], 1)
    z = np.full((n, 1), rest_tip[2])
    return {"square": np.hstack([sq + rest_tip[:2], z]), "lemniscate": np.hstack([lem + rest_tip[:2], z])}


def run_one(method: str, seed: int, args, targets, paths, extra) -> dict:
    """Explore (resuming), then reach and track; the compact result is committed per (method, seed)."""
    out = (RUNS / f"{method}-s{seed}-smoke.json") if args.smoke else (RESULTS / "sopra" / f"{method}-s{seed}.json")
    if out.exists():
        return json.loads(out.read_text())
    run_dir = RUNS / f"{method}-s{seed}{'-smoke' if args.smoke else ''}"
    cfg = make_config("SoPrA-v0", method, PRESETS["quick"] + ["heldout_size=1000"] + extra, episodes=args.episodes,
                      seed=seed, wandb="disabled", task="reach-close" if method == "hucrl" else None)
    explore(cfg, run_dir, progress=True)
    cfg, model, state = load_run(run_dir)
    env = SoPrAEnv("sim", max_steps=10**9, install_signal_handlers=False)
    res = [rollout_to_target(cfg, model, env, tgt, 20, 1000 + i) for i, tgt in enumerate(targets)]
    ret, err = np.array([r[0] for r in res]), np.array([r[1] for r in res])
    row = {"method": method, "seed": seed, "episodes": args.episodes, "transitions": state["num_transitions"],
           "heldout_nmse": state["history"][-1]["heldout_nmse"], "mean_return": float(ret.mean()),
           "mean_error_mm": float(err.mean()), "min_error_mm": float(err.min()), "max_error_mm": float(err.max()),
           "errors_mm": err.tolist(), "tracking": {}}
    for name, path in paths.items():
        tips, e = track(cfg, model, env, path, 7)
        row["tracking"][name] = {"mean_error_mm": float(e.mean()), "max_error_mm": float(e.max()), "tips": tips.tolist()}
    env.close()
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(row, indent=1))
    print(f"{out.name}: error {row['mean_error_mm']:.1f} mm, tracking "
          + ", ".join(f"{k} {v['mean_error_mm']:.1f} mm" for k, v in row["tracking"].items()), flush=True)
    return row


def _pm(values, digits=1) -> str:
    v = np.asarray(values, dtype=float)
    return f"{v.mean():.{digits}f}" + (f" +- {v.std(ddof=1):.{digits}f}" if len(v) > 1 else "")


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--episodes", type=int, default=5)
    p.add_argument("--targets", type=int, default=20)
    p.add_argument("--methods", nargs="+", default=["random", "hucrl", "softae"])
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--smoke", action="store_true", help="tiny model/planner (a functional check, not a result)")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    extra = ["model.num_cells=32", "model.depth=2", "train.epochs=2"] if args.smoke else []
    env = SoPrAEnv("sim", max_steps=10**9, install_signal_handlers=False)
    targets = [env.sample_target() for _ in range(args.targets)]  # the twin's fixed seed: the same every call
    rest = env.reset()["observation"][:3].numpy()
    env.close()
    paths = reference_paths(rest)
    rows = {m: [run_one(m, seed, args, targets, paths, extra) for seed in args.seeds] for m in args.methods}
    seeds = len(args.seeds)
    lines = [f"SoPrA twin, {args.episodes} x 200 exploration steps per method, {args.targets} random targets x 20 "
             f"steps (`quick` preset), mean +- std over {seeds} seed{'s' * (seeds != 1)}"
             f"{' [SMOKE: tiny sizes]' if args.smoke else ''}", "",
             "| method | seeds | held-out nMSE | mean return (ours) | tip error mean / min / max [mm] (ours) | "
             "square / lemniscate tracking error [mm] | paper (real arm): return, error mean / min / max |",
             "|---|---|---|---|---|---|---|"]
    for m, rs in rows.items():
        paper = PAPER.get(m)
        ptxt = f"{paper[0]}, {paper[1]} / {paper[2]} / {paper[3]}" if paper else "-"
        lines.append(
            f"| {m} | {len(rs)} | {_pm([r['heldout_nmse'] for r in rs], 3)} | {_pm([r['mean_return'] for r in rs], 2)} | "
            f"{_pm([r['mean_error_mm'] for r in rs])} / {_pm([r['min_error_mm'] for r in rs])} / "
            f"{_pm([r['max_error_mm'] for r in rs])} | "
            f"{_pm([r['tracking']['square']['mean_error_mm'] for r in rs])} / "
            f"{_pm([r['tracking']['lemniscate']['mean_error_mm'] for r in rs])} | {ptxt} |")
    table = "\n".join(lines)
    print("\n" + table)
    out_dir = RUNS if args.smoke else RESULTS
    (out_dir / "sopra_eval.md").write_text(table + "\n")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    (out_dir / "plots").mkdir(exist_ok=True)
    for name, path in paths.items():
        # one panel per method on shared axes: overlaid, the methods' paths hide each other
        fig, axes = plt.subplots(1, len(rows), figsize=(3.3 * len(rows) + 0.5, 3.6), sharex=True, sharey=True,
                                 squeeze=False)
        for ax, (m, rs) in zip(axes[0], rows.items()):
            ax.plot(path[:, 0] * 1e3, path[:, 1] * 1e3, "k--", lw=1.2, label="reference")
            for r in rs:
                tips = np.array(r["tracking"][name]["tips"])
                ax.plot(tips[:, 0] * 1e3, tips[:, 1] * 1e3, "-", lw=1, alpha=0.8, label=f"seed {r['seed']}")
            ax.set_title(f"{m}: {_pm([r['tracking'][name]['mean_error_mm'] for r in rs]).replace('+-', '±')} mm", fontsize=10)
            ax.set_xlabel("tip x [mm]")
            ax.set_aspect("equal")
        axes[0][0].set_ylabel("tip y [mm]")
        axes[0][-1].legend(fontsize=7, loc="upper right")
        fig.suptitle(f"SoPrA twin: {name} tracking, {args.episodes} x 200 exploration steps, mean tracking error "
                     f"over {seeds} seeds", fontsize=10)
        fig.tight_layout()
        out = out_dir / "plots" / f"sopra_tracking_{name}.png"
        fig.savefig(out, dpi=120)
        plt.close(fig)
        print(out)


if __name__ == "__main__":
    main()
