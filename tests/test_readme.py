"""The README's composition example and the MBPO page's library example run as written."""
import re
from pathlib import Path


def test_readme_composition_example_runs():
    text = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    block = re.search(r"## Composing the pieces\s+```python\n(.*?)```", text, re.S).group(1)
    scope = {}
    exec(compile(block, "README.md", "exec"), scope)
    assert tuple(scope["action"].shape) == (12,)
    assert (scope["action"].abs() <= 1).all()


def test_docs_mbpo_example_runs():
    text = (Path(__file__).resolve().parents[1] / "docs" / "results" / "mbpo.md").read_text()
    block = re.search(r"In code, on the library alone:\s+```python\n(.*?)```", text, re.S).group(1)
    scope = {}
    exec(compile(block, "docs/results/mbpo.md", "exec"), scope)
    assert scope["trainer"].updates == 20 and len(scope["trainer"].imagined) == 400 * 5
    assert tuple(scope["action"].shape) == (1,) and float(scope["action"].abs()) <= 2
