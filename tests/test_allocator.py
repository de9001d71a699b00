"""`train.allocator`: glibc's malloc told to keep freed memory mapped, so a step's large tensors stop faulting
their pages in again every step (page faults counted, not timed)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from gns_bench.devices import apply_allocator

# malloc and memset straight from libc, as torch's CPU allocator gets its memory (numpy would ask for huge pages)
SCRIPT = """
import ctypes, ctypes.util, resource, sys
from gns_bench.devices import apply_allocator
print(apply_allocator(sys.argv[1]))
libc = ctypes.CDLL(ctypes.util.find_library("c"))
libc.malloc.restype, libc.malloc.argtypes = ctypes.c_void_p, [ctypes.c_size_t]
libc.free.argtypes = [ctypes.c_void_p]
faults = lambda: resource.getrusage(resource.RUSAGE_SELF).ru_minflt
def cycle():
    block = libc.malloc(200_000_000)
    ctypes.memset(block, 1, 200_000_000)
    libc.free(block)
cycle()  # once: the heap grows to hold it
before = faults()
for _ in range(5):  # as a training step frees and reallocates its activations
    cycle()
print((faults() - before) / 5)
"""


def faults_per_cycle(setting: str) -> tuple[str, float]:
    env = {k: v for k, v in os.environ.items() if k != "GLIBC_TUNABLES"}
    out = subprocess.run([sys.executable, "-c", SCRIPT, setting], capture_output=True, text=True, env=env,
                         check=True).stdout.splitlines()
    return out[0], float(out[1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_keeping_memory_mapped_stops_the_page_faults_of_a_reallocated_block() -> None:
    used, kept = faults_per_cycle("keep")
    assert used.startswith("glibc malloc kept mapped")
    system, default = faults_per_cycle("system")
    assert system == "system"
    pages = 200e6 / os.sysconf("SC_PAGE_SIZE")
    assert default > 0.5 * pages  # the default maps each 200 MB block afresh: every page faults again
    assert kept < 0.01 * pages  # kept: the block comes back from the heap, already mapped


def test_auto_leaves_an_allocator_the_user_set_alone(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("GLIBC_TUNABLES", "glibc.malloc.mmap_max=0")
    assert apply_allocator("auto") == "system (GLIBC_TUNABLES=glibc.malloc.mmap_max=0)"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_the_bench_row_counts_fewer_faults_with_memory_kept_mapped() -> None:
    """At the size of a real training batch. glibc raises its mmap threshold to the size of each mmapped block
    it frees, up to 32 MiB, so a step whose largest tensors are smaller soon stops mmapping them and the two
    settings fault alike by chance (300 particles: 868 against 1,639 faults a step in one run, 608 against 454 in
    another, AMD EPYC family 26); at 71k edges each [E, 128] latent is 36 MB, above the cap (1.41M against 0)."""
    from gns_bench.bench.allocator import markdown, measure_allocator

    rows = measure_allocator(particles=2600, neighbours=28.0, precisions=("fp32",), steps=2, warmup=2,
                             message_passing_steps=2)  # each block's tensors as the paper's, fewer blocks
    assert rows[0]["edges"] * 128 * 4 > 32 << 20  # the latents above glibc's largest mmap threshold
    by = {r["setting"]: r for r in rows}
    assert by["keep"]["allocator"].startswith("glibc malloc kept mapped") and by["system"]["allocator"] == "system"
    assert by["keep"]["minor_faults_per_step"] < 0.5 * by["system"]["minor_faults_per_step"]
    assert "| fp32 | system |" in markdown(rows, "test machine") and "with M = 2" in markdown(rows, "test machine")
