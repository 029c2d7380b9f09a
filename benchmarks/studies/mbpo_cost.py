"""What MBPO costs on this machine: one SAC update and one imagined-rollout round, and from them
the compute of a run at the paper's settings (Table S8) and at the ``quick`` preset's.

    python benchmarks/studies/mbpo_cost.py                  # the soft arm's sizes (d_s = 58, d_a = 12)
    python benchmarks/studies/mbpo_cost.py --env-dims 3 1   # Pendulum's

Sizes are interleaved (round-robin, ``--repeats`` rounds), each timed as the median and best of
its rounds; the CPU's features are printed. A run's SAC compute is ``updates_per_step x
transitions x (update + rollout round / updates_per_rollout)`` per task policy.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import torch
from tensordict import TensorDict
from torchrl.data import Bounded
from torchrl.envs import TransformedEnv

sys.path.insert(0, str(Path(__file__).parents[1]))
from planning_speed import cpu_description  # noqa: E402

from torchrl_softae.envs import EnsembleModelEnv  # noqa: E402
from torchrl_softae.modules import EnsembleWorldModel  # noqa: E402
from torchrl_softae.objectives import MBPOTrainer, make_sac_actor_critic  # noqa: E402
from torchrl_softae.pipeline.arguments import PRESETS  # noqa: E402
from torchrl_softae.pipeline.config import PolicyConfig, apply_overrides, make_config  # noqa: E402
from torchrl_softae.tasks.base import Task, TaskReward  # noqa: E402


def policy_config(preset: str) -> PolicyConfig:
    cfg = make_config("Pendulum-v1", "softae")
    apply_overrides(cfg, [o for o in PRESETS[preset] if o.startswith("policy.")])
    return cfg.policy


def contender(pcfg: PolicyConfig, d_s: int, d_a: int):
    torch.manual_seed(0)
    model = EnsembleWorldModel(d_s, d_a)  # Table S6 ensemble: 5 x 4 x 256
    obs = torch.randn(1000, d_s)
    model.fit_normalizers(obs, torch.rand(1000, d_a) * 2 - 1, obs + 0.1 * torch.randn(1000, d_s))
    task = Task("dist", lambda s, a, s2: -s2[..., :3].norm(dim=-1), 200)
    env = TransformedEnv(EnsembleModelEnv(model.eval(), action_spec=Bounded(-1.0, 1.0, (d_a,))), TaskReward(task))
    actor, qvalue = make_sac_actor_critic(d_s, env.action_spec, pcfg.num_cells, pcfg.depth)
    trainer = MBPOTrainer(actor, qvalue, task.reward, rollout_horizon=pcfg.rollout_horizon,
                          rollout_batch=pcfg.rollout_batch, updates_per_rollout=pcfg.updates_per_rollout,
                          batch_size=pcfg.batch_size, real_ratio=pcfg.real_ratio)
    real = TensorDict({"observation": obs, "action": torch.rand(1000, d_a) * 2 - 1,
                       "next": {"observation": obs + 0.1 * torch.randn(1000, d_s)}}, [1000])
    trainer.imagine(env, real)
    batch = trainer.sample_batch(real)
    return {"update": lambda: trainer.update(batch), "rollout round": lambda: trainer.imagine(env, real)}


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--env-dims", type=int, nargs=2, default=[58, 12], metavar=("D_S", "D_A"))
    p.add_argument("--transitions", type=int, default=5000, help="real transitions of the run to cost (default 5000)")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    d_s, d_a = args.env_dims
    print(json.dumps(cpu_description()), f"threads {args.threads}")
    presets = {name: policy_config(name) for name in ("paper", "quick")}
    calls = {name: contender(cfg, d_s, d_a) for name, cfg in presets.items()}
    times = {(n, k): [] for n in calls for k in calls[n]}
    for fn in (f for c in calls.values() for f in c.values()):
        fn()  # warm-up
    for _ in range(args.repeats):
        for n, c in calls.items():
            for k, fn in c.items():
                t = time.perf_counter()
                fn()
                times[(n, k)].append(time.perf_counter() - t)
    out = {}
    for n, cfg in presets.items():
        upd, roll = statistics.median(times[(n, "update")]), statistics.median(times[(n, "rollout round")])
        per_update = upd + roll / cfg.updates_per_rollout
        updates = cfg.updates_per_step * args.transitions
        out[n] = {"update_ms_median": 1e3 * upd, "update_ms_best": 1e3 * min(times[(n, "update")]),
                  "rollout_round_ms_median": 1e3 * roll, "updates_per_task": updates,
                  "minutes_per_task_policy": updates * per_update / 60}
        print(f"{n:>6}: SAC {cfg.depth} x {cfg.num_cells}, batch {cfg.batch_size}: update {1e3 * upd:.1f} ms (best "
              f"{1e3 * min(times[(n, 'update')]):.1f}), rollout round of {cfg.rollout_batch} x {cfg.rollout_horizon} "
              f"{1e3 * roll:.1f} ms; {cfg.updates_per_step} updates per real transition x {args.transitions} "
              f"transitions = {updates} updates = {out[n]['minutes_per_task_policy']:.0f} min per task policy")
    path = Path(__file__).parents[1] / "results" / f"mbpo_cost_{d_s}x{d_a}.json"
    path.write_text(json.dumps({"cpu": cpu_description(), "threads": args.threads, "d_s": d_s, "d_a": d_a,
                                "transitions": args.transitions, **out}, indent=1))


if __name__ == "__main__":
    main()
