"""What running a sweep on Ray Tune buys and costs on this 2-core machine.

    python benchmarks/sweep_speed.py           # ~10-15 minutes

The grid of ``sweeps/pendulum_bench.yaml`` (Pendulum-v1, 4 methods x 3 seeds, quick preset,
2 x 100 steps) three times into fresh roots, one after another on an otherwise idle machine:

  ray-1x2    Ray Tune, 1 run at a time with 2 CPUs / torch threads   (--cpus-per-trial 2)
  ray-2x1    Ray Tune, 2 runs at a time with 1 CPU / thread each     (--cpus-per-trial 1)
  local-2x1  2 local processes with 1 thread each, no Ray            (--jobs 2)

and Ray's own cost: ``ray.init`` time and the memory of its processes (GCS, raylet, an idle
worker) right after start. Results: stdout and benchmarks/results/sweep_speed.json.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).parent
SWEEP = HERE.parent / "sweeps" / "pendulum_bench.yaml"


def _sweep(root: Path, *args) -> float:
    t = time.perf_counter()
    subprocess.run([sys.executable, "-m", "torchrl_softae.pipeline.cli", "sweep", str(SWEEP), "--root", str(root), *args],
                   check=True, stdout=subprocess.DEVNULL)
    return time.perf_counter() - t


def ray_cost() -> dict:
    os.environ.setdefault("RAY_AUTH_MODE", "disabled")
    import ray

    t = time.perf_counter()
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    started = time.perf_counter() - t

    @ray.remote
    def ping():
        return os.getpid()

    t = time.perf_counter()
    ray.get(ping.remote())
    first_task = time.perf_counter() - t
    time.sleep(1.0)
    keys = ("gcs_server", "raylet", "ray::", "default_worker", "dashboard", "log_monitor", "runtime_env")
    n, rss = 0, 0
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="ignore")
            if any(k in cmd for k in keys):
                status = Path(f"/proc/{pid}/status").read_text()
                rss += int(next(line.split()[1] for line in status.splitlines() if line.startswith("VmRSS")))
                n += 1
        except (OSError, StopIteration):
            continue
    ray.shutdown()
    return {"ray_init_s": started, "first_task_s": first_task, "ray_processes": n, "ray_rss_mib": rss / 1024}


def main():
    argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter).parse_args()
    work = Path(tempfile.mkdtemp(prefix="sweep_speed_"))
    res = {"cpu": platform.processor() or platform.machine(), "cores": len(os.sched_getaffinity(0)),
           "grid": "Pendulum-v1, 4 methods x 3 seeds, quick preset, 2 episodes x 100 steps"}
    res["ray_cost"] = ray_cost()
    for name, args in (("ray-1x2", ["--cpus-per-trial", "2"]), ("ray-2x1", ["--cpus-per-trial", "1"]),
                       ("local-2x1", ["--jobs", "2"])):
        res[name + "_s"] = _sweep(work / name, *args)
        print(f"{name}: {res[name + '_s']:.0f} s", flush=True)
    res["speedup_2_concurrent"] = res["ray-1x2_s"] / res["ray-2x1_s"]
    res["ray_overhead_per_trial_s"] = (res["ray-2x1_s"] - res["local-2x1_s"]) / 12
    print(json.dumps(res, indent=1))
    (HERE / "results").mkdir(exist_ok=True)
    (HERE / "results" / "sweep_speed.json").write_text(json.dumps(res, indent=1))
    shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
