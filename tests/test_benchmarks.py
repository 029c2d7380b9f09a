"""Every benchmark script still runs after the code it measures has moved: each one's ``--help``
(its imports and argument parser) in one interpreter."""
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = sorted(p for p in (ROOT / "benchmarks").glob("*.py") if not p.name.startswith("_"))


def test_every_benchmark_imports_and_parses_its_arguments():
    assert len(SCRIPTS) >= 10
    code = f"""
import runpy, sys
sys.path.insert(0, {str(ROOT / 'benchmarks')!r})
failed = []
for f in {[str(p) for p in SCRIPTS]!r}:
    sys.argv = [f, "--help"]
    try:
        runpy.run_path(f, run_name="__main__")
        failed.append(f + ": did not stop at --help")
    except SystemExit as e:
        if e.code not in (0, None):
            failed.append(f"{{f}}: exit {{e.code}}")
    except Exception as e:
        failed.append(f"{{f}}: {{type(e).__name__}}: {{e}}")
print("\\nFAILED: ".join(["", *failed]))
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    failed = out.stdout.split("\nFAILED: ")[1:]
    assert not failed, failed
    assert out.stdout.count("usage:") == len(SCRIPTS)
