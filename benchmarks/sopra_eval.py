"""SoPrA (simulated twin): explore with Random, H-UCRL and SoftAE, then reach 20 random targets and
track a square and a lemniscate zero-shot; the paper's real-arm numbers alongside.

    python benchmarks/sopra_eval.py                       # ~15 min on 2 cores
    python benchmarks/sopra_eval.py --episodes 1 --targets 3 --smoke

Exploration: EPISODES x 200 steps per method (``quick`` preset, iCEM H=5, colored-noise exponent
1.0 as in Table S7; H-UCRL is optimistic on the reach-close task reward). Evaluation: 20 targets
drawn uniformly from the twin's reachable workspace (settled tips under random pressures within
the 400 mbar cap), 20 steps each (task horizon of the paper), reward g(d) summed (max 20), final
tip error in mm. Tracking: a 30 mm square and a 40 x 20 mm lemniscate in the horizontal plane
through the rest tip, 80 steps each; the MPC's target moves to the next reference point every
step; error = horizontal distance. Outputs: benchmarks/results/sopra_eval.{md,json},
benchmarks/results/plots/sopra_tracking_*.png.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from torchrl_softae.pipeline.builders import build_planner_policy
from torchrl_softae.pipeline.cli import PRESETS
from torchrl_softae.pipeline.config import make_config
from torchrl_softae.envs.robots.sopra import SoPrAEnv
from torchrl_softae.pipeline.entries.sopra import sopra_reach_task
from torchrl_softae.pipeline.evaluate import load_run
from torchrl_softae.pipeline.explore import explore

RESULTS = Path(__file__).parent / "results"
PAPER = {  # real SoPrA, the paper's table: mean return, mean / min / max tip error [mm]
    "softae": (17.78, 2.00, 0.49, 4.70), "random": (17.63, 3.82, 1.20, 9.57), "hucrl": (15.23, 10.15, 1.14, 49.41),
}


def rollout_to_target(cfg, model, env, target, steps, seed):
    task = sopra_reach_task("target", target, horizon=steps)
    policy = build_planner_policy(model, env.action_spec, cfg.planner, mode="mean", reward=task, seed=seed)
    env.set_seed(seed)
    traj = env.rollout(steps, policy, break_when_any_done=True)
    reward = task.reward(traj["observation"], traj["action"], traj["next", "observation"])
    tips = traj["next", "observation"][:, :3].numpy()
    return float(reward.sum()), float(np.linalg.norm(tips[-1] - target)) * 1e3


def track(cfg, model, env, path, seed):
    """MPC whose target is the next reference point at every step (tensor updated in place)."""
    target = torch.as_tensor(path[0], dtype=torch.float32).clone()
    from torchrl_softae.envs.robots.soft_arm import reach_reward
    from torchrl_softae.tasks.base import Task

    task = Task("track", lambda s, a, s2: reach_reward((s2[..., 0:3] - target).norm(dim=-1)), len(path))
    policy = build_planner_policy(model, env.action_spec, cfg.planner, mode="mean", reward=task, seed=seed)
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


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--episodes", type=int, default=5)
    p.add_argument("--targets", type=int, default=20)
    p.add_argument("--methods", nargs="+", default=["random", "hucrl", "softae"])
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--smoke", action="store_true", help="tiny model/planner (a functional check, not a result)")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    root = RESULTS / "runs" / "sopra"
    extra = ["model.num_cells=32", "model.depth=2", "train.epochs=2"] if args.smoke else []
    env = SoPrAEnv("sim", max_steps=10**9, install_signal_handlers=False)
    targets = [env.sample_target() for _ in range(args.targets)]
    rest = env.reset()["observation"][:3].numpy()
    paths = reference_paths(rest)
    rows, tracking = {}, {}
    for method in args.methods:
        cfg = make_config("SoPrA-v0", method, PRESETS["quick"] + ["heldout_size=1000"] + extra, episodes=args.episodes,
                          seed=args.seed, wandb="disabled", task="reach-close" if method == "hucrl" else None)
        explore(cfg, root / method, progress=True)
        cfg, model, _ = load_run(root / method)
        res = [rollout_to_target(cfg, model, env, tgt, 20, 1000 + i) for i, tgt in enumerate(targets)]
        ret, err = np.array([r[0] for r in res]), np.array([r[1] for r in res])
        rows[method] = {"mean_return": float(ret.mean()), "mean_error_mm": float(err.mean()),
                        "min_error_mm": float(err.min()), "max_error_mm": float(err.max())}
        tracking[method] = {}
        for name, path in paths.items():
            tips, e = track(cfg, model, env, path, 7)
            tracking[method][name] = {"mean_error_mm": float(e.mean()), "max_error_mm": float(e.max()),
                                      "tips": tips.tolist()}
        print(method, rows[method], {k: v["mean_error_mm"] for k, v in tracking[method].items()}, flush=True)
    lines = [f"SoPrA twin, {args.episodes} x 200 exploration steps per method, {args.targets} random targets x 20 steps "
             f"(`quick` preset){' [SMOKE: tiny sizes]' if args.smoke else ''}", "",
             "| method | mean return (ours) | tip error mean / min / max [mm] (ours) | square / lemniscate tracking error [mm] | paper (real arm): return, error mean / min / max |",
             "|---|---|---|---|---|"]
    for m in args.methods:
        r, t = rows[m], tracking[m]
        paper = PAPER.get(m)
        ptxt = f"{paper[0]}, {paper[1]} / {paper[2]} / {paper[3]}" if paper else "-"
        lines.append(f"| {m} | {r['mean_return']:.2f} | {r['mean_error_mm']:.2f} / {r['min_error_mm']:.2f} / "
                     f"{r['max_error_mm']:.2f} | {t['square']['mean_error_mm']:.1f} / {t['lemniscate']['mean_error_mm']:.1f} | {ptxt} |")
    table = "\n".join(lines)
    print("\n" + table)
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "sopra_eval.md").write_text(table + "\n")
    (RESULTS / "sopra_eval.json").write_text(json.dumps({"reach": rows, "tracking": tracking}, indent=1))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    (RESULTS / "plots").mkdir(exist_ok=True)
    for name, path in paths.items():
        fig, ax = plt.subplots(figsize=(4.5, 4))
        ax.plot(path[:, 0] * 1e3, path[:, 1] * 1e3, "k--", label="reference")
        for m in args.methods:
            tips = np.array(tracking[m][name]["tips"])
            ax.plot(tips[:, 0] * 1e3, tips[:, 1] * 1e3, "-", label=f"{m} ({tracking[m][name]['mean_error_mm']:.1f} mm)")
        ax.set_xlabel("tip x [mm]")
        ax.set_ylabel("tip y [mm]")
        ax.set_aspect("equal")
        ax.legend(fontsize=7)
        ax.set_title(f"SoPrA twin: {name} tracking")
        fig.tight_layout()
        out = RESULTS / "plots" / f"sopra_tracking_{name}.png"
        fig.savefig(out, dpi=120)
        plt.close(fig)
        print(out)
    env.close()


if __name__ == "__main__":
    main()
