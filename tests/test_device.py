"""core.device.threads: the one place that narrows a thread's CPU work, and restores it."""
from __future__ import annotations

import torch

from repaint_nerf.core.device import threads


def _fake_count(monkeypatch, start: int) -> tuple[list[int], list[int]]:
    count, calls = [start], []
    monkeypatch.setattr(torch, "get_num_threads", lambda: count[0])

    def set_count(n: int) -> None:
        calls.append(n)
        count[0] = n

    monkeypatch.setattr(torch, "set_num_threads", set_count)
    return count, calls


def test_threads_narrows_and_restores(monkeypatch):
    count, calls = _fake_count(monkeypatch, 2)
    with threads(1):
        assert count[0] == 1
    assert count[0] == 2 and calls == [1, 2]


def test_threads_restores_after_an_error(monkeypatch):
    count, _ = _fake_count(monkeypatch, 4)
    try:
        with threads(2):
            raise RuntimeError("boom")
    except RuntimeError:
        pass
    assert count[0] == 4


def test_threads_that_change_nothing_leave_torch_alone(monkeypatch):
    """None, or at least the current count, never widens the pool and makes no set/restore call on the hot path."""
    count, calls = _fake_count(monkeypatch, 2)
    for n in (None, 2, 8):
        with threads(n):
            assert count[0] == 2
    assert calls == []


_FAULTS = """
import resource, sys
if sys.argv[1] == "1":
    import repaint_nerf.core  # sets THP_MEM_ALLOC_ENABLE before torch's first allocation
import torch
faults = []
for _ in range(3):  # a render's temporaries: large, fresh each time
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    x = torch.empty(40 << 20, dtype=torch.uint8)
    x.fill_(1)
    del x
    faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
print(max(faults[1:]))
"""


def test_large_cpu_tensors_fault_in_huge_pages():
    """Importing core before torch asks PyTorch for transparent huge pages: a fresh 40 MB tensor faults in 2 MB
    pages, not 10k 4 KB ones. Fresh processes: torch reads the setting once."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    import pytest

    mode = Path("/sys/kernel/mm/transparent_hugepage/enabled")
    if not mode.exists() or "[never]" in mode.read_text():
        pytest.skip("the kernel gives no transparent huge pages")
    env = {k: v for k, v in os.environ.items() if k != "THP_MEM_ALLOC_ENABLE"}
    faults = {on: int(subprocess.run([sys.executable, "-c", _FAULTS, on], capture_output=True, text=True,
                                     check=True, env=env).stdout) for on in ("0", "1")}
    assert faults["0"] > 5000  # 40 MB in 4 KB pages: ~10k faults
    assert faults["1"] < faults["0"] / 10  # ~20 huge pages, plus an unaligned edge in small ones
