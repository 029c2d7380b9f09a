"""Does a plan's time depend on which contender ran just before it? The question behind
``planning_speed.py``'s shuffled order (benchmarks/README.md, "The targets").

    python benchmarks/studies/order_effect.py [--rounds 15]

SoPrA's shape ((32, 6), H=5), three of ``planning_speed.py``'s contenders as it runs them: our fp32
one-particle plan followed by its network calls replayed alone (``--network-alone``), then two
identical one-particle bf16 plans (SoftAE's setting: ``icem-bf16-dedup`` and the same planner again,
``B``), in the order fp32, A, B and then fp32, B, A, each order twice, ``--rounds`` rounds each;
then the same with an untimed action of each planner right before its timed one, as
``planning_speed.py`` runs them. If the plan right after the fp32 replay is slower whichever of A
and B it is, the place, not the planner, costs the time. Prints the medians per order; nothing is
written.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch
from tensordict import TensorDict

sys.path.insert(0, str(Path(__file__).parents[1]))
from planning_speed import (  # noqa: E402
    NetworkCallsAlone, RecordNetworkCalls, cpu_description, icem_contender, icem_settings, make_model, pets_env,
    softae_env, use_allocator)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--rounds", type=int, default=15)
    p.add_argument("--threads", type=int, default=2)
    args = p.parse_args()
    if args.rounds < 1 or args.threads < 1:
        p.error(f"--rounds {args.rounds} and --threads {args.threads}: expected at least 1 each")
    use_allocator("kept")
    torch.set_num_threads(args.threads)
    print(f"# order_effect: {cpu_description()['cpu']}, {args.threads} threads, {args.rounds} rounds per order",
          flush=True)
    model = make_model(32, 6)
    sample_env, opt_env = pets_env(model), softae_env(model)
    obs = TensorDict({"observation": torch.randn(32)}, [])
    icem = icem_settings(5)
    planners = {"fp32": icem_contender("icem-fp32-dedup", sample_env, opt_env, icem)[0],
                "A": icem_contender("icem-bf16-dedup", sample_env, opt_env, icem)[0],
                "B": icem_contender("icem-bf16-dedup", sample_env, opt_env, icem)[0]}
    with torch.no_grad():
        for planner in planners.values():
            planner(obs.clone())
        planners["fp32"].reset()
        with RecordNetworkCalls(model) as rec:
            planners["fp32"](obs.clone())
        replay = NetworkCallsAlone(rec, "fp32")
        for own_action_first in (False, True):
            for order in (["fp32", "A", "B"], ["fp32", "B", "A"]) * 2:
                times = {k: [] for k in order}
                for _ in range(args.rounds):
                    for key in order:
                        if own_action_first:  # as planning_speed.py does: an untimed action of its own
                            planners[key].reset()
                            planners[key](obs.clone())
                        planners[key].reset()
                        t = time.perf_counter()
                        planners[key](obs.clone())
                        times[key].append(time.perf_counter() - t)
                        if key == "fp32":
                            replay()
                print(("each after an untimed action of its own: " if own_action_first else "")
                      + " -> ".join(order) + ": "
                      + ", ".join(f"{k} {1e3 * statistics.median(v):.2f} ms" for k, v in times.items()), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
