"""Measured choices of how to run the ensemble at inference: which kernels (grouped 1x1
convolutions through oneDNN, batched matmuls through MKL/cuBLAS, or the whole network in one call
of our own kernels: AMX tiles, or FMA register blocks) and whether bf16 pays.

Which is faster depends on the CPU, not on its vendor (AMD EPYC without AMX: oneDNN's fp32 GEMM
beats MKL's AVX2 path; Intel with AMX: MKL's fp32 GEMM beats oneDNN's), so each choice is timed
once on the real shapes at first use and cached for the process and on disk
(``$TORCHRL_SOFTAE_CACHE/paths.json``, keyed by CPU model and instruction sets, the compiled
SiLU's instruction set and revision, the whole-network kernels' revisions, torch version, thread
count, the candidates and how they were timed), so
a resumed run on the same kind of machine makes the same choice as the run it resumes. Each
candidate is timed in 5 interleaved rounds of at least 2 ms and judged by its best round: on a
shared host, interference only ever adds time. ``model.engine.inference_path`` fixes it (a
benchmark comparing the paths; ``kernels="torch"`` and ``SOFTAE_KERNELS=0`` keep it to the torch ones).
"""
from __future__ import annotations

import json
import os
import threading
import time
from pathlib import Path

import torch

from torchrl_softae.modules.engine import amx_network, fma_network, silu_kernel
from torchrl_softae.modules.engine.precision import cpu_info, cpu_name, flags_of

__all__ = ["choose", "choices", "cache_path", "cpu_key", "INFERENCE_PATHS", "WHOLE_NETWORK_KERNELS"]

#: grouped 1x1 convolutions (oneDNN) with the activation as its own kernel, the same with the
#: activation fused into the convolution (a oneDNN post-op: one pass over the layer's output
#: instead of two), batched matmuls; and the two unfused ones with the SiLU by the compiled kernel
#: (torchrl_softae/modules/engine/csrc/silu.c; candidates only where it was built and the activation is SiLU);
#: and the whole network in one kernel call: bf16 in AMX tiles (with SiLU on a CPU with AMX,
#: csrc/amx_network.c) or in register blocks, fp32 on AVX-512F or AVX2+FMA and bf16 on AVX512-BF16
#: (with SiLU, csrc/fma_network.c)
INFERENCE_PATHS = ("conv", "conv-fused", "bmm", "conv-silu-kernel", "bmm-silu-kernel", "amx-network", "fma-network")
#: the inference paths that run the whole network in one kernel call, and their kernels
#: (``kernel.available(dtype)`` says where and in which dtype: AMX bf16; FMA fp32, and bf16 on
#: AVX512-BF16)
WHOLE_NETWORK_KERNELS = {"amx-network": amx_network, "fma-network": fma_network}
_LOCK = threading.RLock()  # re-entrant: a measured candidate may itself make a measured choice
_MEMORY: dict[str, str] = {}


def cache_path() -> Path:
    root = os.environ.get("TORCHRL_SOFTAE_CACHE") or os.path.join(
        os.environ.get("XDG_CACHE_HOME", os.path.expanduser("~/.cache")), "torchrl_softae")
    return Path(root) / "paths.json"


#: the instruction sets that change which path is fastest; part of the machine's key
#: (x86, then ARM's scalable vectors, BFloat16 and int8 matmul instructions)
_RANKING_FLAGS = ("avx2", "fma", "avx512f", "avx512bw", "avx512_bf16", "amx_bf16", "sve", "bf16", "i8mm")


def cpu_key(info: dict[str, str], silu_tag: str | None) -> str:
    """The CPU as the cache key names it, from its ``/proc/cpuinfo`` fields
    (:func:`~torchrl_softae.modules.engine.precision.cpu_info`). The model name alone is not enough:
    virtual machines of two kinds both report "AMD EPYC", one with AVX-512 and one with AVX2 only,
    and a choice measured on one can be much slower on the other. So the key also has the family,
    model and the instruction sets of :data:`_RANKING_FLAGS`, and which instruction set the
    compiled SiLU runs on and its revision (``silu_tag``, :func:`.silu_kernel.cache_tag`: a rebuilt
    kernel may rank differently). ARM CPUs list no model name
    (:func:`~torchrl_softae.modules.engine.precision.cpu_name` names them by implementer and part), family
    or model."""
    flags = flags_of(info)
    isa = "+".join(f for f in _RANKING_FLAGS if f in flags) or "no listed ISA"
    return (f"{cpu_name(info)}|family {info.get('cpu family', '?')} model {info.get('model', '?')}|{isa}|"
            f"SiLU kernel {silu_tag or 'not built'}")


def _machine() -> str:
    return (f"{cpu_key(cpu_info(), silu_kernel.cache_tag())}|AMX network {amx_network.cache_tag() or 'not run'}|"
            f"FMA network {fma_network.cache_tag() or 'not run'}|"
            f"torch {torch.__version__}|{torch.get_num_threads()} threads")


#: interleaved rounds per candidate; each round repeats a call until it has run this long
_ROUNDS, _ROUND_SECONDS = 5, 0.002
#: part of the cache key: choices measured another way (an older, noisier protocol) are measured again
_PROTOCOL = f"best of {_ROUNDS} rounds of {_ROUND_SECONDS * 1e3:g} ms"


def _per_call(fn) -> float:
    """Seconds per call of ``fn`` over one round: at least one call, repeated until the round has
    lasted ``_ROUND_SECONDS`` (a single call of a small network is too short to time)."""
    calls, t = 0, time.perf_counter()
    while True:
        fn()
        calls += 1
        elapsed = time.perf_counter() - t
        if elapsed >= _ROUND_SECONDS:
            return elapsed / calls


def choices() -> dict[str, str]:
    """The choices this process has made or read so far (key without the machine -> choice): what
    a run's results depend on besides its seed, since kernels differ in their last bits."""
    machine = _machine() + "|"
    with _LOCK:  # another thread may be choosing
        return {k[len(machine):] if k.startswith(machine) else k: v for k, v in _MEMORY.items()}


def choose(key: str, candidates: dict) -> str:
    """The fastest of ``candidates`` (name -> zero-argument callable) for ``key``: measured once
    (interleaved rounds, the best round of each), then remembered in this process and on disk. A candidate that
    raises (a kernel this build or CPU lacks) is not a candidate."""
    full = f"{_machine()}|{key}|{','.join(candidates)}|{_PROTOCOL}"
    with _LOCK:
        if full in _MEMORY:
            return _MEMORY[full]
        path = cache_path()
        disk = {}
        if path.exists():
            try:
                disk = json.loads(path.read_text())
            except (OSError, json.JSONDecodeError):
                disk = {}
        if disk.get(full) in candidates:
            _MEMORY[full] = disk[full]
            return disk[full]
        working = {}
        for name, fn in candidates.items():
            try:
                fn()  # warm-up
            except RuntimeError:
                continue
            working[name] = fn
        if not working:
            raise RuntimeError(f"no candidate of {sorted(candidates)} runs for {key}")
        candidates = working
        # the best round of each, not the median: on a shared host interference only ever adds
        # time, and three single calls once made a choice 20 % slower than its rival stick on disk
        times = {name: [] for name in candidates}
        for _ in range(_ROUNDS):
            for name, fn in candidates.items():
                times[name].append(_per_call(fn))
        best = min(times, key=lambda n: min(times[n]))
        _MEMORY[full] = best
        try:  # merge with what was written meanwhile (nested choices, other processes)
            disk = json.loads(path.read_text()) if path.exists() else {}
        except (OSError, json.JSONDecodeError):
            disk = {}
        disk[full] = best
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
            tmp.write_text(json.dumps(disk, indent=1, sort_keys=True))
            os.replace(tmp, path)
        except OSError:
            pass  # a read-only home: the choice holds for this process
        return best
