"""The one place that decides the torch device, dtypes and thread settings.

Everything in `core` asks here instead of calling `torch.cuda.is_available()` itself, so a user can
force a device with `REPAINT_NERF_DEVICE=cpu|cuda|cuda:1` and tests can pin the CPU.
"""
from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from functools import lru_cache

import torch

ENV_DEVICE = "REPAINT_NERF_DEVICE"


@lru_cache(maxsize=None)
def _resolve(name: str | None) -> torch.device:
    name = name or os.environ.get(ENV_DEVICE) or ("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(name)
    if dev.type == "cuda" and not torch.cuda.is_available():
        from repaint_nerf.core.errors import UserError

        raise UserError(f"device '{name}' was asked for but CUDA is not available",
                        hint=f"unset {ENV_DEVICE} or set it to 'cpu'")
    return dev


def get_device(name: str | None = None) -> torch.device:
    """The device to run on: `name`, else $REPAINT_NERF_DEVICE, else CUDA when present, else CPU."""
    return _resolve(name)


def is_cuda(device: torch.device | str | None = None) -> bool:
    return torch.device(device or get_device()).type == "cuda"


def autocast_dtype(device: torch.device | str | None = None) -> torch.dtype | None:
    """Mixed-precision dtype for the device (fp16 on CUDA), or None where autocast does not pay (CPU)."""
    return torch.float16 if is_cuda(device) else None


def describe(device: torch.device | str | None = None) -> str:
    """A human-readable device description for benchmark JSON and logs."""
    dev = torch.device(device or get_device())
    if dev.type == "cuda":
        return f"cuda:{torch.cuda.get_device_name(dev)}"
    import platform

    return f"cpu:{platform.processor() or platform.machine()} x{torch.get_num_threads()} threads"


def synchronize(device: torch.device | str | None = None) -> None:
    """Wait for queued kernels (timing needs it on CUDA; a no-op on CPU)."""
    if is_cuda(device):
        torch.cuda.synchronize(torch.device(device or get_device()))


def thread_count(n: int | None = None) -> int:
    """How many CPU threads the calling thread's torch ops (and our native kernels) use, or would use inside
    `threads(n)`: at most n, at least 1."""
    now = torch.get_num_threads()
    return now if n is None else max(1, min(int(n), now))


@contextmanager
def threads(n: int | None) -> Iterator[None]:
    """Run the calling thread's CPU work (torch ops and our native kernels) on at most `n` threads, restoring its
    count after; None leaves it. torch's count is per calling thread, so other threads' work is not touched."""
    before, want = torch.get_num_threads(), thread_count(n)
    if want == before:  # nothing to change: no set/restore pair on every render and step
        yield
        return
    torch.set_num_threads(want)
    try:
        yield
    finally:
        torch.set_num_threads(before)
