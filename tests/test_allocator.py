"""keep_freed_memory: a large tensor allocated again and again reuses freed memory instead of
faulting in fresh pages; bad input gets one clear error."""
import subprocess
import sys

import pytest

from torchrl_softae.allocator import keep_freed_memory

# 64 MiB: above glibc's largest mmap threshold (32 MiB), so by default every allocation of it is
# a fresh mapping, faulted in page by page
_REPEATED_ALLOCATION_FAULTS = """
import resource, torch
from torchrl_softae.allocator import keep_freed_memory
applied = keep_freed_memory() if {keep} else None

def touch():
    t = torch.empty(64 << 20, dtype=torch.uint8)
    t.fill_(1)
    return t

for _ in range(16):  # glibc's heap settles: small objects between the chunks pin the first few
    t = touch()    # (2 to 10 of them, measured in fresh processes)
    del t
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(8):
    t = touch()
    del t
print(applied, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def _repeated_allocation_faults(keep: bool) -> tuple[str, int]:
    out = subprocess.run([sys.executable, "-c", _REPEATED_ALLOCATION_FAULTS.format(keep=keep)],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    applied, faults = out.stdout.split()
    return applied, int(faults)


def test_kept_memory_spares_the_page_faults_of_a_repeated_large_allocation():
    applied, kept = _repeated_allocation_faults(keep=True)
    if applied != "True":
        pytest.skip("malloc here is not glibc's: keep_freed_memory does not apply")
    _, default = _repeated_allocation_faults(keep=False)
    if default < 8000:  # 8 x 16384 pages of 4 KiB; a kernel backing them with huge pages faults ~250 times
        pytest.skip(f"this kernel faults 8 tensors of 64 MiB in {default} faults (huge pages): nothing to spare")
    # every one of the 8 faults in by default; kept, at most 2 of them may (the heap still settling)
    assert kept <= default // 4, (kept, default)


@pytest.mark.parametrize("bad", [-1, 2**31, 1.5, True])
def test_keep_freed_memory_rejects_a_bad_size(bad):
    with pytest.raises(ValueError, match=r"retain_bytes=.*expected an int in \[0, 2\*\*31\)"):
        keep_freed_memory(bad)
