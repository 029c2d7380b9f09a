"""The README's composition example runs as written."""
import re
from pathlib import Path


def test_readme_composition_example_runs():
    text = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    block = re.search(r"## Composing the pieces\s+```python\n(.*?)```", text, re.S).group(1)
    scope = {}
    exec(compile(block, "README.md", "exec"), scope)
    assert tuple(scope["action"].shape) == (12,)
    assert (scope["action"].abs() <= 1).all()
