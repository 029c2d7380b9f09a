"""The planning-speed targets, checked against the committed benchmark records of one kind of CPU.

    python benchmarks/speed_targets.py                    # this machine's kind (amx, avx512-bf16 or no-bf16)
    python benchmarks/speed_targets.py --kind amx         # another kind's records
    python benchmarks/speed_targets.py --plot             # also draw them (results/plots/speed_targets-KIND.png)
    python benchmarks/speed_targets.py --kind amx --runs 2026-12-05-sampled-run1 2026-12-05-sampled-run2
                                                          # and each value's range over those runs and the record

Reads ``benchmarks/results/planning_speed-KIND.json`` (``planning_speed.py --compare-paths``) and
``eval_batch_speed-KIND[-bf16].json`` (``eval_batch_speed.py [--precision bf16]``), and prints one
row per target and place: the measured value, the two bounds the same run measured for it where
the record has them, and whether the target is met. "At the GEMM peak": the computation's ensemble
FLOPs at the GEMM peak of its dtype (for bf16 over fp32, the ratio of the two peaks), what any
implementation of the same computation could at best reach on this CPU; over ``CEMPlanner``, which
steps the same model, both planners' FLOPs at the peak, ``CEMPlanner``'s own work outside its
network calls as measured (``planning_speed.shared_model_bound``). "Network calls alone"
(``planning_speed.py --network-alone``): the plan's own network calls, replayed alone in the same
rounds, i.e. the value if everything but the network cost nothing (over ``CEMPlanner``: its plan
over our calls; bf16 over fp32: the fp32 calls over the bf16 calls; ms: the calls' time). The targets are the performance
issue's, in one place (:data:`TARGETS`); nothing is measured here, so the table is exactly what
the records say. Ratios are of medians; "% of peak" is the record's (best round).

``--runs TAG ...`` adds two columns: each value's range, and its bounds' ranges, over the record and
the runs named by their file tags (``planning_speed-KIND-TAG.json``,
``eval_batch_speed-KIND[-bf16]-TAG.json``; a run without one of those files counts for the targets
of the others), so the spread of a set of runs of the same code is printed, not copied by hand.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from planning_speed import best_peaks, cpu_description, cpu_kind, shared_model_bound  # noqa: E402

RESULTS = Path(__file__).parent / "results"
KINDS = ("amx", "avx512-bf16", "no-bf16")
#: planning_speed shape -> (where, in the table; the robot, in the per-robot targets' names)
SHAPES = {"arm58": ("arm (58, 12), H=10", "arm"), "sopra32-H5": ("SoPrA (32, 6), H=5", "SoPrA")}

#: the kinds with native bf16: the bf16 targets apply there only (elsewhere torch emulates bf16,
#: precision="auto" plans in fp32 and planning_speed.py times no bf16 contender)
BF16_KINDS = ("amx", "avx512-bf16")
#: (name, the kinds it applies to or None for every kind, comparison, threshold)
TARGETS = [
    ("10 particles fp32 vs no-grad CEMPlanner", None, ">=", 1.3),
    ("1 particle fp32 vs no-grad CEMPlanner", None, ">=", 6.0),
    ("10 particles bf16 vs best fp32", ("amx",), ">=", 3.5),
    ("1 particle bf16 vs best fp32", ("amx",), ">=", 2.5),
    ("10 particles bf16 vs best fp32", ("avx512-bf16",), ">=", 1.8),
    ("1 particle bf16 vs best fp32", ("avx512-bf16",), ">=", 1.4),
    ("10 particles fp32, % of the fp32 peak", None, ">=", 70),
    ("1 particle fp32, % of the fp32 peak", None, ">=", 45),
    ("10 particles bf16, % of the bf16 peak", BF16_KINDS, ">=", 50),
    ("1 particle bf16, % of the bf16 peak", BF16_KINDS, ">=", 25),
    ("SoftAE (1 particle bf16) ms per action, arm", ("amx",), "<=", 40),
    ("SoftAE (1 particle bf16) ms per action, SoPrA", ("amx",), "<=", 20),
    ("8 episodes as one batch vs one after another", None, ">=", 3.0),
]


def applies(target_kinds: tuple | None, kind: str) -> bool:
    """Whether a target of :data:`TARGETS` applies to CPUs of ``kind``."""
    return target_kinds is None or kind in target_kinds


def _load(name: str) -> dict | None:
    path = RESULTS / name
    return json.loads(path.read_text()) if path.exists() else None


def measured_rows(kind: str, run_tag: str | None = None) -> list[tuple]:
    """``(target, where, measured, bound at the GEMM peak or None, bound of the network calls alone or
    None)`` for every target of ``kind`` its records cover: the record, or the run of file tag
    ``run_tag``."""
    run = "" if run_tag is None else f"-{run_tag}"
    out = []
    planning = _load(f"planning_speed-{kind}{run}.json")
    if planning is not None:
        peak = best_peaks(planning["peaks_gflops"])
        peak_ratio = peak["bf16"] / peak["fp32"] if "bf16" in peak else None
        for shape, (where, robot) in SHAPES.items():
            rows = {r["planner"]: r for r in planning["rows"] if r["shape"] == shape}
            if not rows:
                continue
            cem = rows["cem-torchrl"]["median_s"]
            for particles, tag in (("10 particles", "full"), ("1 particle", "dedup")):
                fp32 = rows[f"icem-fp32-{tag}"]
                out.append((f"{particles} fp32 vs no-grad CEMPlanner", where, fp32["speedup_vs_cem_median"],
                            shared_model_bound(rows["cem-torchrl"], fp32),
                            cem / fp32["network_alone_s"] if "network_alone_s" in fp32 else None))
                out.append((f"{particles} fp32, % of the fp32 peak", where, 100 * fp32["fraction_of_peak"], None, None))
                bf16 = rows.get(f"icem-bf16-{tag}")
                if bf16 is None:  # a CPU without native bf16: no bf16 contender was timed
                    continue
                alone = "network_alone_s" in fp32 and "network_alone_s" in bf16
                best_fp32 = min(r["median_s"] for k, r in rows.items() if k.split("@")[0] == f"icem-fp32-{tag}")
                out.append((f"{particles} bf16 vs best fp32", where, best_fp32 / bf16["median_s"], peak_ratio,
                            fp32["network_alone_s"] / bf16["network_alone_s"] if alone else None))
                out.append((f"{particles} bf16, % of the bf16 peak", where, 100 * bf16["fraction_of_peak"], None, None))
            bf16 = rows.get("icem-bf16-dedup")
            if bf16 is not None:
                out.append((f"SoftAE (1 particle bf16) ms per action, {robot}", where, 1e3 * bf16["median_s"],
                            1e3 * bf16["seconds_at_peak"] if "seconds_at_peak" in bf16 else None,
                            1e3 * bf16["network_alone_s"] if "network_alone_s" in bf16 else None))
    for suffix, prec in (("", "fp32"), ("-bf16", "bf16")):
        batched = _load(f"eval_batch_speed-{kind}{suffix}{run}.json")
        if batched is None:
            continue
        for env_id, row in batched["envs"].items():
            out.append(("8 episodes as one batch vs one after another", f"{env_id}, {prec}", row["speedup_median"],
                        row.get("max_speedup_at_peak"), row.get("max_speedup_network_alone")))
    return out


def checked_rows(kind: str) -> list[tuple]:
    """``(target, comparison, threshold, where, measured, at the peak, network alone, met)`` per
    target of ``kind`` and place, in :data:`TARGETS`' order (measured ``None``: no record)."""
    by_name = {}
    for name, where, value, at_peak, alone in measured_rows(kind):
        by_name.setdefault(name, []).append((where, value, at_peak, alone))
    out = []
    for name, kinds, op, threshold in TARGETS:
        if not applies(kinds, kind):
            continue
        for where, value, at_peak, alone in by_name.get(name, [("(no record)", None, None, None)]):
            met = None if value is None else (value >= threshold if op == ">=" else value <= threshold)
            out.append((name, op, threshold, where, value, at_peak, alone, met))
    return out


def run_ranges(kind: str, tags: list[str]) -> tuple[dict, list[str]]:
    """``{(target, where): (measured values, bounds at the GEMM peak, bounds of the network calls
    alone)}`` over the record and the runs of ``tags`` (a run without a bound adds none), and the
    tags that have no record file at all."""
    values, missing = {}, []
    for tag in [None, *tags]:
        rows = measured_rows(kind, tag)
        if not rows:
            missing.append(tag)
        for name, where, *found in rows:
            for kept, value in zip(values.setdefault((name, where), ([], [], [])), found):
                if value is not None:
                    kept.append(value)
    return values, missing


def value_range(values: list[float], fmt) -> str:
    """``lowest-highest`` in ``fmt``, the unit written once (``1.16-1.19x``)."""
    lo, hi = fmt(min(values)), fmt(max(values))
    return lo if lo == hi else f"{lo.removesuffix('x')}-{hi}"


def plot(rows: list[tuple], kind: str, cpu: str, path: Path) -> None:
    """``rows`` (of :func:`checked_rows`, measured and with a bound) on one axis: value over the
    target (target over value for times), so 1 is the target and right of it is met; the measured
    median and the two bounds."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    def rel(op, threshold, v):
        return None if v is None else (v / threshold if op == ">=" else threshold / v)

    fig, ax = plt.subplots(figsize=(9, 0.42 * len(rows) + 2.0))
    for y, (name, op, threshold, where, value, at_peak, alone, met) in enumerate(rows):
        m, a, n = rel(op, threshold, value), rel(op, threshold, at_peak), rel(op, threshold, alone)
        right = max(v for v in (m, a, n) if v is not None)
        ax.plot([min(v for v in (m, a, n) if v is not None), right], [y, y], color="0.85", lw=6, zorder=1,
                solid_capstyle="butt")
        if a is not None:
            ax.scatter(a, y, marker="|", s=250, color="0.45", zorder=2,
                       label="at the GEMM peak (over CEMPlanner: the shared model at it for both)" if y == 0 else None)
        if n is not None:
            ax.scatter(n, y, marker="D", s=40, facecolor="white", edgecolor="tab:blue", zorder=3,
                       label="its network calls alone" if y == 0 else None)
        ax.scatter(m, y, s=55, color="tab:green" if met else "tab:red", zorder=4)
        ax.annotate(f"{value:.0f} ms" if "ms" in name else f"{value:.2f}x", (m, y), xytext=(-5, 6),
                    textcoords="offset points", ha="right", va="bottom", fontsize=7, zorder=5,
                    bbox={"boxstyle": "square,pad=0.1", "facecolor": "white", "edgecolor": "none"})
    ax.scatter([], [], s=55, color="tab:green", label="measured (median), met")
    ax.scatter([], [], s=55, color="tab:red", label="measured (median), not met")
    ax.axvline(1.0, color="k", lw=1, ls="--")
    ax.set_yticks(range(len(rows)))
    ax.set_yticklabels([f"{name} {op} {threshold:g}\n{where}" for name, op, threshold, where, *_ in rows], fontsize=7)
    ax.set_ylim(len(rows) - 0.5, -0.75)  # top to bottom, with room above the first row's label
    ax.set_xscale("log")
    lo, hi = ax.get_xlim()
    lo, hi = lo / 1.12, hi * 1.03  # room for the value labels left of the leftmost points
    ax.set_xlim(lo, hi)
    ticks = [t for t in (0.25, 0.3, 0.4, 0.5, 0.6, 0.8, 1, 1.25, 1.5, 2, 2.5, 3, 4, 6, 8) if lo <= t <= hi]
    ax.xaxis.set_major_locator(matplotlib.ticker.FixedLocator(ticks))
    ax.xaxis.set_major_formatter(matplotlib.ticker.FuncFormatter(lambda v, _: f"{v:g}"))
    ax.xaxis.set_minor_locator(matplotlib.ticker.NullLocator())
    ax.set_xlabel("measured / target (for ms: target / measured), log scale: 1 = the target, right of it = met")
    ax.set_title(f"Planning-speed targets on {cpu} ({kind}, benchmarks/results/*-{kind}*.json):\n"
                 "measured medians, and the bounds measured in the same run", fontsize=9)
    ax.grid(axis="x", which="both", alpha=0.3)
    # below the axis label, in a strip of its own: inside the axes it would cover rows of a short figure
    fig.legend(*ax.get_legend_handles_labels(), fontsize=7, loc="lower center", ncol=2, frameon=False)
    fig.tight_layout(rect=(0, 0.55 / fig.get_figheight(), 1, 1))
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=130)
    plt.close(fig)


def targets_table(kind: str, checked: list[tuple], ranges: dict, runs: list[str]) -> str:
    """The targets of ``kind`` as a markdown table (with each value's range over ``runs``)."""
    record = _load(f"planning_speed-{kind}.json") or _load(f"eval_batch_speed-{kind}.json")
    out = [f"# speed targets on {kind} ({record['cpu']['cpu']}), from benchmarks/results/*-{kind}*.json"]
    # the allocator setting moves plan times (benchmarks/studies/allocator_speed.py): say which each record ran with
    names = [f"planning_speed-{kind}.json", f"eval_batch_speed-{kind}.json", f"eval_batch_speed-{kind}-bf16.json"]
    out.append("allocator: " + "; ".join(f"{n} {r.get('allocator', 'default (recorded before the option)')}"
                                         for n in names if (r := _load(n)) is not None) + "\n")
    spread = (" measured over the runs (how many, the record included) | bounds over them: at the GEMM peak; "
              "network calls alone |") if runs else ""
    out.append(f"| target | where | measured | at the GEMM peak | its network calls alone | met |{spread}")
    out.append("|---|---|---|---|---|---|" + ("---|---|" if runs else ""))
    for name, op, threshold, where, value, at_peak, alone, met in checked:
        if value is None:
            out.append(f"| {name} {op} {threshold:g} | {where} | not measured | | | |" + (" | |" if runs else ""))
            continue
        fmt = (lambda v: f"{v:.0f}") if "%" in name or "ms" in name else (lambda v: f"{v:.2f}x")
        if fmt(value) == fmt(threshold):  # a value that rounds onto its threshold: show which side it is on
            fmt = (lambda v: f"{v:.1f}") if "%" in name or "ms" in name else (lambda v: f"{v:.3f}x")
        bounds = " | ".join("" if b is None else fmt(b) for b in (at_peak, alone))
        line = f"| {name} {op} {threshold:g} | {where} | {fmt(value)} | {bounds} | {'yes' if met else 'no'} |"
        if runs:
            measured, peak_bounds, alone_bounds = ranges[(name, where)]
            bounds = "; ".join(value_range(b, fmt) if b else "" for b in (peak_bounds, alone_bounds))
            line += f" {value_range(measured, fmt)} ({len(measured)}) | {bounds if bounds != '; ' else ''} |"
        out.append(line)
    return "\n".join(out)


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--kind", choices=KINDS, default=None, help="default: this machine's kind")
    p.add_argument("--plot", action="store_true", help="also draw the targets and their bounds on one axis")
    p.add_argument("--runs", nargs="+", default=[], metavar="TAG",
                   help="also print each value's range over the record and these runs (file tags, e.g. "
                        "2026-12-05-sampled-run1 for planning_speed-KIND-2026-12-05-sampled-run1.json)")
    args = p.parse_args()
    kind = args.kind or cpu_kind(cpu_description())
    checked = checked_rows(kind)
    if all(row[4] is None for row in checked):
        p.exit(2, f"speed_targets: no records for kind {kind!r} in {RESULTS} (run planning_speed.py and "
                  f"eval_batch_speed.py on such a CPU first)\n")
    ranges, missing = run_ranges(kind, args.runs) if args.runs else ({}, [])
    if missing:
        p.exit(2, f"speed_targets: --runs {' '.join(missing)}: no planning_speed-{kind}-TAG.json or "
                  f"eval_batch_speed-{kind}[-bf16]-TAG.json in {RESULTS}\n")
    print(targets_table(kind, checked, ranges, args.runs))
    record = _load(f"planning_speed-{kind}.json") or _load(f"eval_batch_speed-{kind}.json")
    if args.plot:
        path = RESULTS / "plots" / f"speed_targets-{kind}.png"
        drawable = [r for r in checked if r[4] is not None and (r[5], r[6]) != (None, None)]
        if drawable:
            cpu = record["cpu"]
            plot(drawable, kind, f"{cpu['cpu']}, {'AVX-512' if cpu.get('avx512f') else 'no AVX-512'}", path)
            print(f"\nwrote {path}")
        else:
            print(f"\nnothing to draw: the {kind} records have no bounds (rerun planning_speed.py with "
                  f"--network-alone and eval_batch_speed.py on such a CPU)")
    if any("with_logvar" not in r for r in record.get("rows", [])):
        print("\n(this planning record predates 2026-12-03: its % of peak counts the log-variance head for every "
              "row, about 6 % too high for the 1-particle rows, and it has no bounds at the peak)")


if __name__ == "__main__":
    main()
