"""Why the arm's models lose to s' = s on the held-out set: the size of one step in the explored data
against the held-out set's, and the model's error on each, by group of state dimensions.

    python benchmarks/studies/arm_delta_scale.py RUN [RUN ...]       # finished run dirs of SoftArm-v1
    python benchmarks/studies/arm_delta_scale.py --table              # the committed results

Every quantity is in units of the held-out metric's normalizer (the reference set's std per
dimension), as root mean square over the transitions and the group's dimensions: ``delta``, one
step's change ``s' - s`` (what s' = s gets wrong); ``error``, the run's own model's ``mu - s'``, on
its last 2,000 explored transitions and on the held-out set. ``flips``: the share of explored
transitions where a segment's quaternion changes by more than 1 in norm (the ``w >= 0``
convention flips its sign near a half turn: a jump the delta model must learn, not a motion).
Results: ``benchmarks/results/arm_delta_scale/RUN.json``.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

RESULTS = Path(__file__).parents[1] / "results" / "arm_delta_scale"


def study(run_dir: str) -> dict:
    from torchrl_softae.envs.robots.soft_arm import arm_layout
    from torchrl_softae.pipeline.catalog import get_env_entry
    from torchrl_softae.pipeline.data import ModelAccuracy
    from torchrl_softae.pipeline.evaluate import load_run
    from torchrl_softae.pipeline.policy import stored_transitions
    from torchrl_softae.pipeline.runs import RunDir

    cfg, model, state = load_run(run_dir)
    run = RunDir(run_dir)
    data = stored_transitions(run, state)
    accuracy = ModelAccuracy(get_env_entry(cfg.env), run, cfg.heldout_size)
    _, std, kept = accuracy.scale
    scale = torch.where(kept, std, torch.ones_like(std))
    held = accuracy.heldout
    last = slice(max(len(data) - 2000, 0), len(data))

    def rms(x, idx):
        return float(x[:, idx].square().mean().sqrt())

    with torch.no_grad():
        own = (model.predict(data["observation"][last], data["action"][last])[0] - data["next", "observation"][last]) / scale
        out = (model.predict(held["observation"], held["action"])[0] - held["next", "observation"]) / scale
    explored = (data["next", "observation"] - data["observation"]) / scale
    heldout = (held["next", "observation"] - held["observation"]) / scale
    quats = arm_layout(cfg.observed_points if hasattr(cfg, "observed_points") else 5)["orientations"]
    jumps = (data["next", "observation"][:, quats] - data["observation"][:, quats]).reshape(len(data), -1, 4)
    flips = float((jumps.norm(dim=-1) > 1.0).any(-1).float().mean())
    groups = {g: {"delta_explored": rms(explored, idx), "delta_heldout": rms(heldout, idx),
                  "error_own_data": rms(own, idx), "error_heldout": rms(out, idx)}
              for g, idx in accuracy.groups.items()}
    return {"run": Path(run_dir).name, "env": cfg.env, "method": cfg.method, "seed": cfg.seed,
            "episodes": state["episode"] + 1, "transitions": len(data), "quaternion_flips": flips, "groups": groups}


def table() -> str:
    import numpy as np

    results = [json.loads(p.read_text()) for p in sorted(RESULTS.glob("*.json"))]
    groups = list(results[0]["groups"])
    lines = ["| method | n | quaternion flips | " + " | ".join(
        f"{g.replace('_', ' ')}: delta explored / held-out; error own / held-out" for g in groups) + " |",
             "|---|---|---|" + "---|" * len(groups)]
    for method in dict.fromkeys(r["method"] for r in results):
        rs = [r for r in results if r["method"] == method]
        mean = lambda key, g: np.mean([r["groups"][g][key] for r in rs])  # noqa: E731
        cells = [f"{mean('delta_explored', g):.2f} / {mean('delta_heldout', g):.2f}; "
                 f"{mean('error_own_data', g):.2f} / {mean('error_heldout', g):.2f}" for g in groups]
        lines.append(f"| {method} | {len(rs)} | {np.mean([r['quaternion_flips'] for r in rs]):.3f} | "
                     + " | ".join(cells) + " |")
    return "\n".join(lines)


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("runs", nargs="*", help="finished run dirs")
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
        print(f"{result['run']}: flips {result['quaternion_flips']:.3f}, " + ", ".join(
            f"{g} {v['delta_explored']:.2f}/{v['delta_heldout']:.2f} err {v['error_heldout']:.2f}"
            for g, v in result["groups"].items()), flush=True)


if __name__ == "__main__":
    main()
