"""Which instruction-set variant a compiled kernel runs on (``csrc/isa_variants.h``), as the
kernels' Python modules (:mod:`.silu_kernel`, :mod:`.moments_kernel`) expose it."""
from __future__ import annotations

from types import ModuleType
from typing import Callable


def instruction_set_functions(
    extension: ModuleType | None,
) -> tuple[Callable[[], str | None], Callable[[], list[str]], Callable[[str], None]]:
    """``isa()``, ``supported_isas()`` and ``use_isa(name)`` of a compiled ``extension`` (``None``
    where it was not built or this CPU runs none of its variants)."""

    def isa() -> str | None:
        """The instruction set the kernel runs on (the best this CPU has), ``None`` without it."""
        return None if extension is None else extension.isa()

    def supported_isas() -> list[str]:
        """The instruction sets this CPU can run the kernel on, worst to best (empty without it)."""
        return [] if extension is None else extension.supported_isas()

    def use_isa(name: str) -> None:
        """Run the kernel on ``name`` (one of :func:`supported_isas`): for tests and measurements."""
        if name not in supported_isas():
            raise ValueError(f"use_isa: {name!r} is not one of this CPU's {supported_isas()}")
        extension.use_isa(name)

    return isa, supported_isas, use_isa
