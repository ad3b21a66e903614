"""Tests of deliffas.engine.memory.retain_freed_memory (in subprocesses: it changes the allocator)."""

from __future__ import annotations

import subprocess
import sys

import pytest

_PROBE = """
import resource, sys
import torch
from deliffas.engine.memory import retain_freed_memory
applied = retain_freed_memory() if sys.argv[1] == "retain" else None
def faults():
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt
torch.set_num_threads(1)
conv = torch.nn.Conv2d(32, 32, 3, padding=1, bias=False)
x = torch.rand(1, 32, 256, 256)
steady = []
with torch.inference_mode():
    for i in range(12):  # a render loop: the same 8 MiB conv output allocated and freed every frame
        before = faults()
        conv(x)
        steady.append(faults() - before)
print(applied, sum(steady[-4:]))  # once glibc's free lists have settled
"""


def _second_allocation_faults(mode: str) -> tuple[str, int]:
    out = subprocess.run([sys.executable, "-c", _PROBE, mode], capture_output=True, text=True, check=True)
    applied, faults = out.stdout.split()
    return applied, int(faults)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc malloc tuning is Linux-only")
def test_retained_memory_is_not_faulted_in_again():
    """With glibc's defaults a conv's freed 8 MiB output is returned to the system and its 2048+
    pages fault in again on every call; after retain_freed_memory() the loop reuses heap memory."""
    applied, retained = _second_allocation_faults("retain")
    if applied != "True":
        pytest.skip("not glibc: retain_freed_memory() changes nothing")
    _, default = _second_allocation_faults("default")
    assert retained < 400, f"retained: expected no page faults, got {retained} in 4 calls"
    # glibc's default sometimes keeps a freed block for a call or two (4075 in 4 calls seen in a loaded CI
    # run, 2048+ per call when quiet): what the fix must show is that it faults far less than the default.
    assert default > retained + 2000, f"default allocator: expected 2048+ page faults per call, got {default} in 4"
