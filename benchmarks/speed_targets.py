"""The planning-speed targets, checked against the committed benchmark records of one kind of CPU.

    python benchmarks/speed_targets.py                    # this machine's kind (amx, avx512-bf16 or no-bf16)
    python benchmarks/speed_targets.py --kind amx         # another kind's records

Reads ``benchmarks/results/planning_speed-KIND.json`` (``planning_speed.py --compare-paths``) and
``eval_batch_speed-KIND[-bf16].json`` (``eval_batch_speed.py [--precision bf16]``), and prints one
row per target and place: the measured value, the bound the same run measured for it where the
record has one (the computation's ensemble FLOPs at the GEMM peak of its dtype; for bf16 over
fp32, the ratio of the two peaks) and whether the target is met. The targets are the performance
issue's, in one place (:data:`TARGETS`); nothing is measured here, so the table is exactly what
the records say. Ratios are of medians; "% of peak" is the record's (best round).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from planning_speed import best_peaks, cpu_description, cpu_kind  # noqa: E402

RESULTS = Path(__file__).parent / "results"
KINDS = ("amx", "avx512-bf16", "no-bf16")
#: planning_speed shape -> (where, in the table; the robot, in the per-robot targets' names)
SHAPES = {"arm58": ("arm (58, 12), H=10", "arm"), "sopra32-H5": ("SoPrA (32, 6), H=5", "SoPrA")}

#: (name, kind it applies to or None for every kind, comparison, threshold)
TARGETS = [
    ("10 particles fp32 vs no-grad CEMPlanner", None, ">=", 1.3),
    ("1 particle fp32 vs no-grad CEMPlanner", None, ">=", 6.0),
    ("10 particles bf16 vs best fp32", "amx", ">=", 3.5),
    ("1 particle bf16 vs best fp32", "amx", ">=", 2.5),
    ("10 particles bf16 vs best fp32", "avx512-bf16", ">=", 1.8),
    ("1 particle bf16 vs best fp32", "avx512-bf16", ">=", 1.4),
    ("10 particles fp32, % of the fp32 peak", None, ">=", 70),
    ("1 particle fp32, % of the fp32 peak", None, ">=", 45),
    ("10 particles bf16, % of the bf16 peak", None, ">=", 50),
    ("1 particle bf16, % of the bf16 peak", None, ">=", 25),
    ("SoftAE (1 particle bf16) ms per action, arm", "amx", "<=", 40),
    ("SoftAE (1 particle bf16) ms per action, SoPrA", "amx", "<=", 20),
    ("8 episodes as one batch vs one after another", None, ">=", 3.0),
]


def _load(name: str) -> dict | None:
    path = RESULTS / name
    return json.loads(path.read_text()) if path.exists() else None


def measured_rows(kind: str) -> list[tuple]:
    """``(target, where, measured, bound or None)`` for every target of ``kind`` its records cover."""
    out = []
    planning = _load(f"planning_speed-{kind}.json")
    if planning is not None:
        peak = best_peaks(planning["peaks_gflops"])
        peak_ratio = peak["bf16"] / peak["fp32"]
        for shape, (where, robot) in SHAPES.items():
            rows = {r["planner"]: r for r in planning["rows"] if r["shape"] == shape}
            if not rows:
                continue
            for particles, tag in (("10 particles", "full"), ("1 particle", "dedup")):
                fp32 = rows[f"icem-fp32-{tag}"]
                out.append((f"{particles} fp32 vs no-grad CEMPlanner", where, fp32["speedup_vs_cem_median"],
                            fp32.get("max_speedup_vs_cem")))
                best_fp32 = min(r["median_s"] for k, r in rows.items() if k.split("@")[0] == f"icem-fp32-{tag}")
                bf16 = rows[f"icem-bf16-{tag}"]
                out.append((f"{particles} bf16 vs best fp32", where, best_fp32 / bf16["median_s"], peak_ratio))
                for prec, row in (("fp32", fp32), ("bf16", bf16)):
                    out.append((f"{particles} {prec}, % of the {prec} peak", where, 100 * row["fraction_of_peak"],
                                None))
            bf16 = rows["icem-bf16-dedup"]
            out.append((f"SoftAE (1 particle bf16) ms per action, {robot}", where, 1e3 * bf16["median_s"],
                        1e3 * bf16["seconds_at_peak"] if "seconds_at_peak" in bf16 else None))
    for suffix, prec in (("", "fp32"), ("-bf16", "bf16")):
        batched = _load(f"eval_batch_speed-{kind}{suffix}.json")
        if batched is None:
            continue
        for env_id, row in batched["envs"].items():
            out.append(("8 episodes as one batch vs one after another", f"{env_id}, {prec}", row["speedup_median"],
                        row.get("max_speedup_at_peak")))
    return out


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--kind", choices=KINDS, default=None, help="default: this machine's kind")
    args = p.parse_args()
    kind = args.kind or cpu_kind(cpu_description())
    rows = measured_rows(kind)
    if not rows:
        p.exit(2, f"speed_targets: no records for kind {kind!r} in {RESULTS} (run planning_speed.py and "
                  f"eval_batch_speed.py on such a CPU first)\n")
    record = _load(f"planning_speed-{kind}.json") or _load(f"eval_batch_speed-{kind}.json")
    print(f"# speed targets on {kind} ({record['cpu']['cpu']}), from benchmarks/results/*-{kind}*.json\n")
    print("| target | where | measured | at the GEMM peak | met |")
    print("|---|---|---|---|---|")
    by_name = {}
    for name, where, value, bound in rows:
        by_name.setdefault(name, []).append((where, value, bound))
    for name, applies, op, threshold in TARGETS:
        if applies not in (None, kind):
            continue
        for where, value, bound in by_name.get(name, [("(no record)", None, None)]):
            if value is None:
                print(f"| {name} {op} {threshold:g} | {where} | not measured | | |")
                continue
            met = value >= threshold if op == ">=" else value <= threshold
            fmt = (lambda v: f"{v:.0f}") if "%" in name or "ms" in name else (lambda v: f"{v:.2f}x")
            bound_txt = "" if bound is None else fmt(bound)
            print(f"| {name} {op} {threshold:g} | {where} | {fmt(value)} | {bound_txt} | {'yes' if met else 'no'} |")
    if any("with_logvar" not in r for r in record.get("rows", [])):
        print("\n(this planning record predates 2026-12-03: its % of peak counts the log-variance head for every "
              "row, about 6 % too high for the 1-particle rows, and it has no bounds at the peak)")


if __name__ == "__main__":
    main()
