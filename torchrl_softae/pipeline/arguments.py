"""The arguments of ``softae explore``, shared by the CLI and sweeps: presets, the explore flags,
turning parsed arguments into a validated config, and where a run goes by default."""
from __future__ import annotations

import argparse
import os

from torchrl_softae.pipeline.methods import METHOD_NAMES, get_method

__all__ = ["PRESETS", "available_cores", "add_explore_args", "config_from_args", "explore_parser", "run_dir_for"]

_SYMLOG = ["model.symlog=true"]  # the paper's MBPO experiments train the model on symlog observations

PRESETS = {
    "paper": [],
    # Small enough for a laptop-minute demo; the method is unchanged, only sizes/steps shrink.
    "quick": [
        "model.num_cells=128", "model.depth=3", "planner.num_candidates=100", "planner.top_k=10",
        "planner.optim_steps=3", "planner.num_particles=5", "train.lr=1e-3", "train.epochs=20",
        "train.max_grad_steps=600", "heldout_size=1000",
        # SAC on the model (MBPO methods, softae policy): same algorithm, smaller networks and budget
        "policy.num_cells=128", "policy.depth=2", "policy.rollout_batch=100", "policy.updates_per_rollout=10",
        "policy.updates_per_step=5", "policy.imagined_capacity=50000", "policy.lr=1e-3",
    ],
}
PRESETS["mbpo"] = PRESETS["paper"] + _SYMLOG  # supplement, "Model-Based Policy Optimization"
PRESETS["mbpo-quick"] = PRESETS["quick"] + _SYMLOG


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity, e.g. under ``taskset``), not the machine's."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def add_explore_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--env", default="Pendulum-v1",
                   help="a catalog id (see `softae envs`), a registered gymnasium id (Reacher-v5), module:EnvId-v0 "
                        "or module:callable returning a gymnasium or TorchRL env; default Pendulum-v1")
    p.add_argument("--method", default="softae", help=f"one of {', '.join(METHOD_NAMES)}; default softae")
    p.add_argument("--episodes", type=int, default=None, help="exploration episodes N (default 10)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--run-dir", default=None, help="output folder; an existing run with the same settings resumes "
                                                   "(default runs/ENV/METHOD-bBETA-sSEED)")
    p.add_argument("--episode-length", type=int, default=None, help="exploration horizon T (env default)")
    p.add_argument("--beta", type=float, default=None,
                   help="optimism beta for the methods that use it (default: the paper's, Table S6)")
    p.add_argument("--task", default=None, help="the task of the methods that optimize one (hucrl, mbpo, mbpo-ts): "
                                                "a task of the env, or module:attr naming your own Task")
    p.add_argument("--heldout", default=None, metavar="FILE",
                   help="your own held-out transitions for the model-accuracy metric: a TensorDict saved with "
                        "torch.save, or a memmap directory, with observation, action, ('next', 'observation') "
                        "(default: the env's held-out set; outside the catalog, random-action episodes)")
    p.add_argument("--coverage-dims", default=None, metavar="I,J",
                   help="the two state dimensions of the coverage grid (default: the env's projection; "
                        "outside the catalog, 0,1)")
    p.add_argument("--eval-every", type=int, default=None, help="zero-shot evaluate all tasks every K episodes (0 = never)")
    p.add_argument("--preset", choices=sorted(PRESETS), default="paper",
                   help="paper: Table S6/S7 sizes; quick: small model/planner/SAC for demos and tests; mbpo, "
                        "mbpo-quick: the same with a symlog-observation model (the paper's MBPO experiments)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override any config field, e.g. --set planner.horizon=5 --set train.lr=1e-4 (repeatable)")
    p.add_argument("--wandb", choices=["offline", "online", "disabled"], default="offline",
                   help="W&B tracking (default offline: no network needed; `wandb sync RUN/wandb/...` later)")
    p.add_argument("--threads", type=int, default=None,
                   help="torch threads (default: the cores this process may use). Two runs side by side on "
                        "2 cores: give each --threads 1 (or taskset -c 0 / -c 1), else both slow down 10x+")
    p.add_argument("--quiet", action="store_true",
                   help="no progress output (a resumed run still says so in one line)")


def config_from_args(args):
    from torchrl_softae.pipeline.config import make_config

    overrides = PRESETS[args.preset] + list(args.overrides)
    return make_config(
        args.env, args.method, overrides, episodes=args.episodes, seed=args.seed, episode_length=args.episode_length,
        beta=args.beta, task=args.task, eval_every=args.eval_every, wandb=args.wandb,
        heldout_file=None if args.heldout is None else os.path.abspath(args.heldout), coverage_dims=args.coverage_dims,
    )


def run_dir_for(cfg, root: str = "runs") -> str:
    """``ROOT/ENV/NAME`` with the name the method table gives (beta only where the method uses it);
    ENV is the env reference as given, a ``/`` in it (``ALE/Pong-v5``) written ``-``."""
    return os.path.join(root, cfg.env.replace("/", "-"), get_method(cfg.method).run_name(cfg.seed, cfg.beta))


def explore_parser() -> argparse.ArgumentParser:
    """A parser of ``softae explore``'s flags alone (what sweep files may set)."""
    p = argparse.ArgumentParser(prog="softae explore", add_help=False)
    add_explore_args(p)
    return p
