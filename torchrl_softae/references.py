"""Objects named by a ``"module:attribute"`` string (an env factory, a task), imported on demand.

Like ``python -m`` (and gymnasium's ``"module:EnvId"`` ids), the module is also looked for in the
current directory: ``softae explore --env myarm:make_arm`` finds ``./myarm.py`` although the
``softae`` script's own directory is first on ``sys.path``.
"""
from __future__ import annotations

import importlib
import os
import sys
from types import ModuleType

__all__ = ["BadReference", "split_reference", "import_reference_module"]


class BadReference(ValueError):
    """A reference names nothing usable; the message names the value and what was expected."""


def split_reference(text: str) -> tuple[str, str] | None:
    """``"pkg.mod:attr"`` -> ``("pkg.mod", "attr")``; ``None`` for a plain name (no colon)."""
    if ":" not in text:
        return None
    module, attr = text.split(":", 1)
    if not module or not attr:
        raise BadReference(f"{text!r}: expected MODULE:ATTRIBUTE with both parts non-empty")
    return module, attr


def import_reference_module(module: str, text: str) -> ModuleType:
    """Import ``module`` (of the reference ``text``), searching the current directory last."""
    try:
        return _import(module)
    except ModuleNotFoundError as e:
        if e.name is None or not module.startswith(e.name.split(".")[0]) or os.getcwd() in sys.path:
            raise BadReference(f"{text!r}: cannot import module {module!r} ({e})") from None
    sys.path.append(os.getcwd())  # the module itself was not found: look where the user stands
    try:
        return _import(module)
    except ModuleNotFoundError as e:
        raise BadReference(f"{text!r}: cannot import module {module!r} ({e}; searched sys.path and the "
                           f"current directory {os.getcwd()})") from None


def _import(module: str) -> ModuleType:
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError:
        raise
    except Exception as e:  # the user's module raised while importing: one line, not its traceback
        raise BadReference(f"importing {module!r} raised {type(e).__name__}: {e}") from None
