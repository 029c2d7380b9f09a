"""The results pages' tables, rendered from the committed results (never copied by hand).

    python benchmarks/results_pages.py           # rewrites every generated block of docs/results/*.md and README.md
    python benchmarks/results_pages.py --check   # exit 1 naming each block that differs

A page marks each block it does not write by hand:

    <!-- generated: KEY -->
    ...
    <!-- end generated -->

and ``KEY`` names what renders it:

- ``sweep:NAME``: the tables of the committed report of a sweep,
  ``benchmarks/results/sweeps/NAME/report.json`` (``softae report --merge`` of its run archive; a
  report from before reports archived their runs has only its tables: its ``report.md``'s);
- ``replication:ENV``: ``softae report`` of the replication records in
  ``benchmarks/results/replication/ENV/`` (one table per budget);
- ``file:PATH``: a table a benchmark script wrote to a committed file (e.g.
  ``benchmarks/results/sopra_eval.md``, by ``benchmarks/sopra_eval.py``);
- ``scorecard``: the judged claims of ``benchmarks/results/replication/scorecard.json`` (claim,
  paper, ours, verdict) and the ids still untested, for the README;
- ``cost:ENV``: what the replication runs in ``benchmarks/results/replication/ENV/`` cost, per
  method (hours per run, the evaluations' share, the machine);
- ``speed:KIND[:TAG,...]``: the planning-speed targets of the records of a CPU kind, with each
  value's range over the runs ``TAG`` (``benchmarks/speed_targets.py``).
"""
from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PAGES = ROOT / "docs" / "results"
#: the pages with generated blocks: every results page and the README (its results table)
BLOCK = re.compile(r"(<!-- generated: (?P<key>[^ ]+) -->\n)(?P<body>.*?)(<!-- end generated -->)", re.S)


def _report_body(markdown: str) -> str:
    """A ``softae report`` markdown without its first heading (it names a temporary folder) and the
    list of the earlier reports its runs came from (the page names its source)."""
    lines = markdown.splitlines()[1:]
    if "## Runs from earlier reports (their run dirs are not below the root)" in lines:
        start = lines.index("## Runs from earlier reports (their run dirs are not below the root)")
        end = next((i for i in range(start + 1, len(lines)) if lines[i].startswith("## ")), len(lines))
        lines = lines[:start] + lines[end:]
    return "\n".join(lines).strip()


def _sweep(name: str) -> str:
    from torchrl_softae.pipeline.report import report

    archive = ROOT / "benchmarks" / "results" / "sweeps" / name / "report.json"
    if "runs" not in json.loads(archive.read_text()):
        return _report_body(archive.with_suffix(".md").read_text())
    text, *_ = report(archive.parent / "merged", plots=False, warn=lambda m: None, merge=[archive], write=False)
    return _report_body(text)


def _replication(env: str) -> str:
    from torchrl_softae.pipeline.report import report

    text, *_ = report(ROOT / "benchmarks" / "results" / "replication" / env, plots=False, warn=lambda m: None,
                      write=False)
    return _report_body(text)


def _speed(spec: str) -> str:
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import speed_targets

    kind, _, tags = spec.partition(":")
    runs = tags.split(",") if tags else []
    ranges, missing = speed_targets.run_ranges(kind, runs) if runs else ({}, [])
    if missing:
        raise ValueError(f"speed:{spec}: no records for the runs {', '.join(missing)}")
    table = speed_targets.targets_table(kind, speed_targets.checked_rows(kind), ranges, runs)
    return table.split("\n", 1)[1].strip()  # the page has its own heading


def _scorecard(_: str) -> str:
    rows = json.loads((ROOT / "benchmarks" / "results" / "replication" / "scorecard.json").read_text())["claims"]
    out = ["| claim | paper | ours | verdict |", "|---|---|---|---|"]
    for r in rows:
        if r["verdict"] != "untested":
            p = "" if r["p"] is None else (f", p = {r['p']:.2g}" if r["p"] >= 1e-3 else ", p < 0.001")
            cells = [f"{r['id']} {r['claim']}", r["paper"], f"{r['ours']}{p}", f"**{r['verdict']}**"]
            out.append("| " + " | ".join(str(c).replace("|", "/") for c in cells) + " |")
    untested = [r["id"] for r in rows if r["verdict"] == "untested"]
    if untested:
        out += ["", f"Untested so far, each with the runs and CPU-hours it needs in the scorecard: {', '.join(untested)}."]
    return "\n".join(out)


def _cost(env: str) -> str:
    """Per method, budget and machine, the hours per run of every run whose records reach that
    budget (its last): the mean and range over the runs, CPU time where every record carries it."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import scorecard

    from torchrl_softae.pipeline.labels import label_order

    last: dict[tuple, dict] = {}
    for path in (scorecard.RESULTS / env).glob("*-ep*.json"):
        r = json.loads(path.read_text())
        if "seconds" in r and r["budget"] > last.get((r["method"], r["seed"]), {}).get("budget", 0):
            last[r["method"], r["seed"]] = r
    # in the order of softae report's tables; a machine per row, since hours differ by machine
    groups: dict[tuple, list[dict]] = {}
    rank = {m: i for i, m in enumerate(label_order(m for m, _ in last))}
    for (method, seed), r in sorted(last.items(), key=lambda kv: (rank[kv[0][0]], kv[0][1])):
        groups.setdefault((method, r["budget"], scorecard.machine_label(r)), []).append(r)

    def spread(costs, total, evaluate):
        values = [c[total] for c in costs]
        return (f"{sum(values) / len(values):.2f} ({min(values):.2f}-{max(values):.2f}), "
                f"{sum(c[evaluate] for c in costs) / len(costs):.2f} evaluating")

    if not groups:
        return f"No records of {env} yet."
    out = ["| method | runs (seeds) | episodes | CPU-hours per run, mean (range) | wall-clock hours per run, "
           "mean (range) | machine |", "|---|---|---|---|---|---|"]
    for (method, budget, machine), runs in groups.items():
        costs = [scorecard.run_cost(env, method, r["seed"], budget) for r in runs]
        cells = [method, f"{len(runs)} ({', '.join(str(r['seed']) for r in runs)})", budget,
                 spread(costs, "hours", "evaluate") if all(c["cpu"] for c in costs) else "not recorded",
                 spread(costs, "wall", "wall_evaluate"), machine]
        out.append("| " + " | ".join(map(str, cells)) + " |")
    return "\n".join(out)


def _file(path: str) -> str:
    return (ROOT / path).read_text().strip()


RENDERERS = {"sweep": _sweep, "replication": _replication, "scorecard": _scorecard, "file": _file, "speed": _speed,
             "cost": _cost}


def render(key: str) -> str:
    kind, _, arg = key.partition(":")
    if kind not in RENDERERS:
        raise ValueError(f"generated block {key!r}: expected one of {', '.join(k + ':...' for k in RENDERERS)}")
    return RENDERERS[kind](arg)


def render_page(text: str) -> str:
    """``text`` with every generated block rendered anew."""
    return BLOCK.sub(lambda m: f"{m.group(1)}{render(m.group('key'))}\n{m.group(4)}", text)


def pages() -> list[Path]:
    return [*sorted(PAGES.glob("*.md")), ROOT / "README.md"]


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--check", action="store_true", help="only compare: exit 1 if a page differs")
    args = p.parse_args()
    stale = []
    for page in pages():
        text = page.read_text()
        new = render_page(text)
        if new != text:
            stale.append(page.relative_to(ROOT))
            if not args.check:
                page.write_text(new)
    blocks = sum(len(BLOCK.findall(p.read_text())) for p in pages())
    if args.check:
        print(f"{len(stale)} of the pages with generated blocks differ from the committed results: "
              + (", ".join(map(str, stale)) or "none") + f" ({blocks} blocks)")
        return 1 if stale else 0
    print(f"rendered {blocks} blocks; rewrote " + (", ".join(map(str, stale)) or "nothing"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
