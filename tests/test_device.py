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
