"""Run-time detection of a fast reduced-precision matmul on this CPU."""
from __future__ import annotations

import functools
import platform

import torch

__all__ = ["cpu_flags", "cpu_info", "cpu_name", "flags_of", "parse_cpuinfo", "fast_bf16_available", "onednn_bf16_available", "resolve_planning_dtype"]


def parse_cpuinfo(text: str) -> dict[str, str]:
    """The first processor's fields of ``/proc/cpuinfo``'s ``text`` (name -> value): on x86 every
    processor's block repeats them."""
    info: dict[str, str] = {}
    for line in text.splitlines():
        if not line.strip():
            break
        name, _, value = line.partition(":")
        info.setdefault(name.strip(), value.strip())
    return info


@functools.lru_cache(maxsize=1)
def cpu_info() -> dict[str, str]:
    """This CPU's ``/proc/cpuinfo`` fields (:func:`parse_cpuinfo`; empty off Linux)."""
    try:
        with open("/proc/cpuinfo") as f:
            return parse_cpuinfo(f.read())
    except OSError:
        return {}


def flags_of(info: dict[str, str]) -> frozenset:
    """The feature flags of :func:`parse_cpuinfo`'s fields: x86 lists them as ``flags``, ARM
    (aarch64) as ``Features`` (where ``bf16`` is the BFloat16 instructions)."""
    return frozenset((info.get("flags") or info.get("Features") or "").split())


def cpu_name(info: dict[str, str]) -> str:
    """The CPU's name from :func:`parse_cpuinfo`'s fields: x86's ``model name``; ARM lists none,
    so its implementer and part number; else the vendor, else ``"unknown"``."""
    if "model name" in info:
        return info["model name"]
    if "CPU part" in info:
        return f"ARM implementer {info.get('CPU implementer', '?')} part {info['CPU part']}"
    return info.get("vendor_id", "unknown")


@functools.lru_cache(maxsize=1)
def cpu_flags() -> frozenset:
    """CPU feature flags from /proc/cpuinfo (empty off Linux)."""
    return flags_of(cpu_info())


def fast_bf16_available() -> bool:
    """``True`` when bf16 matmuls run natively: AMX-BF16 or AVX512-BF16 on x86, the BFloat16
    instructions on aarch64 Linux (macOS has no /proc/cpuinfo: fp32 there)."""
    flags = cpu_flags()
    if {"amx_bf16", "avx512_bf16"} & flags:
        return True
    return platform.machine() in ("arm64", "aarch64") and "bf16" in flags


@functools.lru_cache(maxsize=1)
def onednn_bf16_available() -> bool:
    """``True`` when oneDNN's own bf16 convolutions run on this CPU (AVX512-BW/VL/DQ or
    AVX-NE-CONVERT; torch's own check). Without it ``torch.ops.mkldnn._convolution_pointwise`` and
    its weight pre-packing raise for bf16 (seen on an AMD EPYC with AVX2 only), and ``F.conv2d``
    falls back to a reference kernel; fp32 is unaffected."""
    try:
        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):
        return False


def resolve_planning_dtype(precision: str, device=None) -> torch.dtype | None:
    """Map ``"fp32" | "bf16" | "auto"`` to the hidden-layer dtype (``None`` = fp32) on ``device``.

    ``"auto"`` picks bf16 only where the device has native bf16 units (a CPU with AMX-BF16 or
    AVX512-BF16, a CUDA device that supports bf16); ``"bf16"`` forces it (correct everywhere,
    but slower than fp32 without hardware support).
    """
    if precision == "fp32":
        return None
    if precision == "bf16":
        return torch.bfloat16
    if precision == "auto":
        device = torch.device(device if device is not None else "cpu")
        if device.type == "cuda":
            return torch.bfloat16 if torch.cuda.is_bf16_supported() else None
        if device.type == "cpu":
            return torch.bfloat16 if fast_bf16_available() else None
        return None
    raise ValueError(f"precision={precision!r}, expected one of 'fp32', 'bf16', 'auto'")
