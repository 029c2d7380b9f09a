"""Latency of SoPrA's watchdog: from the last command of a stalled controller to the vent.

    python benchmarks/sopra_watchdog.py            # 100 trials on the twin, control period 50 ms

Each trial: reset the twin env (watchdog on), three steps at full action, then the "planner"
sleeps 10 control periods. The safety layer's watchdog thread must vent within the window
(``watchdog_periods`` x control period = 150 ms) plus its poll period; the latency recorded is the
wall-clock time from the last command to the moment the watchdog vents (taken under the bus lock,
right before the vent is sent). Results: stdout and benchmarks/results/sopra_watchdog.json.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict

from torchrl_softae.envs.robots.sopra import SoPrAEnv


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--trials", type=int, default=100)
    p.add_argument("--period", type=float, default=0.05)
    p.add_argument("--out", default=str(Path(__file__).parent / "results" / "sopra_watchdog.json"))
    args = p.parse_args()
    env = SoPrAEnv("sim", control_period=args.period, install_signal_handlers=False, watchdog=True)
    env.twin.p.mocap_dropout = 0.0
    window = env.limits.watchdog_periods * args.period
    act = TensorDict({"action": torch.ones(6)}, [])
    vented, missed = 0, 0
    for trial in range(args.trials):
        env.set_seed(trial)
        env.reset()
        for _ in range(3):
            env.step(act.clone())
        before = len(env.safety.watchdog_trips)
        time.sleep(10 * args.period)
        if len(env.safety.watchdog_trips) > before and (env.safety.last_command == 0).all():
            vented += 1
        else:
            missed += 1
        env.step(act.clone())  # reports the fault, ends the episode
    lat = np.array(env.safety.watchdog_trips) * 1e3
    env.close()
    q = np.percentile(lat, [0, 50, 90, 99, 100])
    res = {"cpu": platform.processor() or platform.machine(), "cores": len(os.sched_getaffinity(0)),
           "trials": args.trials, "control_period_s": args.period, "window_ms": window * 1e3, "vented": vented,
           "missed": missed, "latency_ms": {"min": q[0], "median": q[1], "p90": q[2], "p99": q[3], "max": q[4],
                                            "mean": float(lat.mean()), "std": float(lat.std())}}
    print(f"watchdog window {window * 1e3:.0f} ms, {args.trials} trials: vented {vented}, missed {missed}")
    print("latency last command -> vent [ms]: min {:.1f}, median {:.1f}, p90 {:.1f}, p99 {:.1f}, max {:.1f}".format(*q))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
