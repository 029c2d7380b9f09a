"""The "Your own robot" tutorial runs as written: its files are written from the page's titled code
blocks and its shell commands run in order, in a fresh folder, as a reader would run them."""
import json
import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

PAGE = Path(__file__).parents[1] / "docs" / "tutorials" / "your-own-robot.md"
FENCE = re.compile(r'^```(\w+)(?:\s+title="([^"]+)")?\n(.*?)^```$', re.MULTILINE | re.DOTALL)


def tutorial_steps(text: str) -> list[tuple[str, str]]:
    """``("file", NAME, CONTENT)`` for every titled block and ``("run", COMMAND)`` for every line of
    a bash block, in page order."""
    steps = []
    for lang, title, body in FENCE.findall(text):
        if title:
            steps.append(("file", title, body))
        elif lang == "bash":
            steps += [("run", line.strip()) for line in body.splitlines() if line.strip()]
    return steps


def test_the_page_has_what_the_tutorial_promises():
    steps = tutorial_steps(PAGE.read_text())
    files = [s[1] for s in steps if s[0] == "file"]
    runs = [s[1] for s in steps if s[0] == "run"]
    assert files == ["myarm.py", "mytasks.py", "my_sweep.yaml"]
    assert [r.split()[1] for r in runs] == ["explore", "evaluate", "sweep", "report"]


def test_your_own_robot_runs_as_written(tmp_path):
    softae = shutil.which("softae", path=os.path.dirname(sys.executable)) or shutil.which("softae")
    assert softae, "the softae script is not installed"
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}  # the reader's folder, nothing else
    env["HOME"] = str(tmp_path / "home")
    for step in tutorial_steps(PAGE.read_text()):
        if step[0] == "file":
            (tmp_path / step[1]).write_text(step[2])
            continue
        argv = shlex.split(step[1])
        proc = subprocess.run([softae, *argv[1:]], cwd=tmp_path, env=env, capture_output=True, text=True)
        assert proc.returncode == 0, f"$ {step[1]}\n{proc.stdout[-2000:]}\n{proc.stderr[-3000:]}"
        if argv[1] == "explore":
            assert "held-out set: random-action episodes (favours Random)" in proc.stdout
    run = tmp_path / "runs" / "myarm" / "softae"
    state = json.loads((run / "config.json").read_text())["config"]
    assert state["env"] == "myarm:MyArm-v0" and state["episode_length"] == 40
    far = json.loads((run / "eval" / "reach-far@horizon=5.json").read_text())
    assert far["success_metric"] == "final_error_mm" and len(far["metrics"]) == 1
    sweep = tmp_path / "runs" / "sweep"
    assert len(list(sweep.rglob("checkpoint.pt"))) == 6
    md = (sweep / "report.md").read_text()
    assert "| random | 3 |" in md and "| softae" in md and "reach-far@horizon=5 final error [mm]" in md
    assert "*held-out set: random-action episodes (favours Random)*" in md
