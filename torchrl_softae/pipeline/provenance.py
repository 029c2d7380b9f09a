"""Which code and which machine computed a result: what a replication record names, and what an
evaluation must share with a saved result before it keeps that result instead of computing it again."""
from __future__ import annotations

import hashlib
import subprocess
from pathlib import Path

__all__ = ["code_version", "code_identity", "machine"]


def _git(*args) -> str:
    """``git ARGS`` in the package's source tree: its output, or ``""`` outside a git checkout."""
    try:
        return subprocess.run(["git", *args], cwd=Path(__file__).resolve().parent, capture_output=True, text=True,
                              timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return ""


def code_version() -> dict:
    """The commit of the package's source tree and whether it had uncommitted changes (``None``
    outside a git checkout): a record says which code computed it."""
    commit = _git("rev-parse", "HEAD") or None
    return {"commit": commit, "dirty": None if commit is None else bool(_git("status", "--porcelain",
                                                                          "--untracked-files=no"))}


def code_identity() -> dict:
    """:func:`code_version`, the package version (an install outside git has no commit), and a
    digest of the uncommitted changes to tracked files (``None`` without any): equal only for the
    same code, also in a working tree being edited."""
    from torchrl_softae import __version__

    code = code_version()
    changes = _git("diff", "HEAD") if code["dirty"] else ""
    return {**code, "version": __version__,
            "changes_sha256": hashlib.sha256(changes.encode()).hexdigest() if changes else None}


def machine() -> dict:
    """The CPU (name and the instruction sets that change the arithmetic or its speed), torch and
    its threads, and which compiled kernels this process loaded."""
    import torch

    from torchrl_softae.modules.engine import amx_network, fma_network, moments_kernel, normal_kernel, silu_kernel
    from torchrl_softae.modules.engine.precision import cpu_info, cpu_name, flags_of

    info = cpu_info()
    flags = flags_of(info)
    return {"cpu": cpu_name(info), "isa": [f for f in ("avx2", "avx512f", "avx512_bf16", "amx_bf16") if f in flags],
            "torch": torch.__version__, "threads": torch.get_num_threads(),
            "kernels": {m.__name__.rsplit(".", 1)[1]: m.available() for m in
                        (amx_network, fma_network, moments_kernel, normal_kernel, silu_kernel)}}
