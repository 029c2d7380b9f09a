"""The one switch between our compiled kernels (``torchrl_softae/modules/engine/csrc``) and pure torch.

``kernels="auto"`` (the default where a model is built) runs a kernel wherever it is built, applies
and measured faster; ``kernels="torch"`` never runs one for that model. The environment variable
``SOFTAE_KERNELS=0`` turns every kernel off in the process (read at import): the path an install
without a C compiler takes, so that it can be tested on any machine.
"""
from __future__ import annotations

import importlib
import os
from types import ModuleType

from torchrl_softae.modules.ensemble import KERNEL_CHOICES  # the model's kernels= choices

__all__ = ["KERNEL_CHOICES", "ENABLED", "kernels_allowed", "load_extension"]

#: ``False`` while ``SOFTAE_KERNELS=0``: no compiled kernel runs in this process
ENABLED: bool = os.environ.get("SOFTAE_KERNELS", "1") != "0"


def kernels_allowed(choice: str = "auto") -> bool:
    """Whether an object built with ``kernels=choice`` may run compiled kernels."""
    if choice not in KERNEL_CHOICES:
        raise ValueError(f"kernels={choice!r}: expected one of {', '.join(KERNEL_CHOICES)}")
    return choice == "auto" and ENABLED


def load_extension(name: str) -> ModuleType | None:
    """The compiled extension ``torchrl_softae.modules.engine.NAME``, or ``None`` where it was not built
    or ``SOFTAE_KERNELS=0``: its wrapper then takes the torch path, as in an install without a C
    compiler. Import torch first: the extension's libgomp.so.1 then resolves to torch's, one
    OpenMP thread pool."""
    if not ENABLED:
        return None
    try:
        return importlib.import_module(f"torchrl_softae.modules.engine.{name}")
    except ImportError:
        return None
