"""Where a run's held-out error comes from: held-out transitions inside or outside its explored data.

    python benchmarks/studies/heldout_extrapolation.py benchmarks/results/runs/arm136_v1/pets-ae-s1 [RUN_DIR ...]

For each run dir (any env; the groups are the env's accuracy groups), from its final model and
replay buffer, the env's held-out set and the reference scale the pipeline uses (read from the
run dir or the per-user cache, never rebuilt here):

- how broad the explored data is beside the held-out set: per group, the std of the next state
  and of the state change, explored / held-out;
- the share of held-out transitions whose input (s, a) leaves the box of the explored inputs
  (per-dimension min and max), and the held-out nMSE of each group inside and outside that box
  (the run's ``heldout_nmse/GROUP`` is their weighted mean);
- per exploration episode, the rms of each group in the explored states, and how much the
  actions switch: the mean ``|a_t - a_(t-1)|`` over steps and action dimensions, beside its value
  for i.i.d. uniform actions in the env's bounds (``(high - low) / 3``, the Random baseline's).

Writes ``benchmarks/results/heldout_extrapolation/<env>-<method>-s<seed>-ep<episodes>.json``
(``--out-dir`` to change).
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from torchrl_softae.pipeline.catalog import get_env_entry
from torchrl_softae.pipeline.data import heldout_set, normalized_mse, reference_scale, reference_set
from torchrl_softae.pipeline.evaluate import load_run
from torchrl_softae.pipeline.runs import RunDir

RESULTS = Path(__file__).parents[1] / "results" / "heldout_extrapolation"


@torch.no_grad()
def extrapolation_report(run_dir: Path) -> dict:
    cfg, model, state = load_run(run_dir)
    run = RunDir(run_dir)
    entry = get_env_entry(cfg.env)
    _, action_spec = entry.specs()
    explored = run.read_transitions(state)
    heldout = heldout_set(entry, run, cfg.heldout_size)
    scale = reference_scale(reference_set(entry, run, heldout))
    kept = scale[2]
    groups = {"all": list(range(model.observation_dim)), **entry.accuracy_groups}

    inputs = lambda td: torch.cat([td["observation"], td["action"]], -1)  # noqa: E731
    x, box = inputs(heldout), inputs(explored)
    outside = ((x < box.min(0).values) | (x > box.max(0).values)).any(-1)
    # the run's own metric (pipeline.data.normalized_mse) on the whole held-out set and on each side
    nmse = {side: normalized_mse(model, heldout[mask], groups, scale)[1] if mask.any() else None
            for side, mask in (("all", torch.ones_like(outside)), ("inside", ~outside), ("outside", outside))}

    def spread(td, dims):
        obs, nxt = td["observation"][:, dims], td["next", "observation"][:, dims]
        return nxt.std(0).mean(), (nxt - obs).std(0).mean()

    length = cfg.episode_length
    episodes = explored.shape[0] // length
    per_episode = explored[: episodes * length].reshape(episodes, length)
    low, high = action_spec.space.low, action_spec.space.high
    report = {"run": str(run_dir), "env": cfg.env, "method": cfg.method, "seed": cfg.seed,
              "episodes": state["episode"] + 1, "transitions": explored.shape[0],
              "heldout_transitions": heldout.shape[0], "heldout_outside_share": float(outside.float().mean()),
              "action_change_per_episode": [float(v) for v in per_episode["action"].diff(dim=1).abs().mean((1, 2))],
              # E|u - u'| for u, u' i.i.d. uniform on [low, high] is (high - low) / 3
              "action_change_uniform": float(((high - low) / 3).mean()),
              "groups": {}}
    for name, dims in groups.items():
        dims = torch.as_tensor(dims)
        dims = dims[kept[dims]]
        if not dims.numel():
            continue
        (e_std, e_delta), (h_std, h_delta) = spread(explored, dims), spread(heldout, dims)
        report["groups"][name] = {
            "nmse": nmse["all"][name],
            "nmse_inside": nmse["inside"][name] if nmse["inside"] else None,
            "nmse_outside": nmse["outside"][name] if nmse["outside"] else None,
            "std_ratio": float(e_std / h_std),
            "delta_std_ratio": float(e_delta / h_delta),
            "rms_per_episode": [float(v) for v in per_episode["observation"][..., dims].square().mean((1, 2)).sqrt()],
            "heldout_rms": float(heldout["observation"][:, dims].square().mean().sqrt()),
        }
    return report


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run_dirs", nargs="+", type=Path, metavar="RUN_DIR")
    p.add_argument("--out-dir", type=Path, default=RESULTS)
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    for run_dir in args.run_dirs:
        r = extrapolation_report(run_dir)
        print(f"{r['env']} {r['method']} seed {r['seed']}, {r['episodes']} episodes ({r['transitions']} transitions): "
              f"{100 * r['heldout_outside_share']:.0f} % of the {r['heldout_transitions']} held-out inputs leave "
              "the box of the explored inputs")
        change = ", ".join(f"{v:.2f}" for v in r["action_change_per_episode"])
        print(f"mean |a_t - a_(t-1)| by episode: {change} (i.i.d. uniform actions: {r['action_change_uniform']:.2f})")
        print("| group | nMSE | inside | outside | explored std / held-out | state change std ratio | "
              "rms by episode | held-out rms |")
        print("|---|---|---|---|---|---|---|---|")
        fmt = lambda v: "-" if v is None else f"{v:.3g}"  # noqa: E731
        for name, g in r["groups"].items():
            rms = ", ".join(f"{v:.2g}" for v in g["rms_per_episode"])
            print(f"| {name} | {fmt(g['nmse'])} | {fmt(g['nmse_inside'])} | {fmt(g['nmse_outside'])} | "
                  f"{g['std_ratio']:.2f} | {g['delta_std_ratio']:.2f} | {rms} | {g['heldout_rms']:.2g} |")
        args.out_dir.mkdir(parents=True, exist_ok=True)
        out = args.out_dir / f"{r['env']}-{r['method']}-s{r['seed']}-ep{r['episodes']}.json"
        out.write_text(json.dumps(r, indent=1))
        print(out)


if __name__ == "__main__":
    main()
