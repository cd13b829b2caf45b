"""Small native CPU kernels: built from C on first use with the system compiler, cached, loaded through ctypes.

Each kernel source is compiled into a per-user cache keyed by the hash of its source and flags, so an
edited source rebuilds and concurrent builders never load a half-written library. When no compiler is
available (or $REPAINT_NERF_NATIVE=0) a kernel warns once and its callers take their PyTorch path.
"""
from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import shutil
import subprocess
import tempfile
import threading
import warnings
from collections.abc import Callable
from pathlib import Path

ENV_NATIVE = "REPAINT_NERF_NATIVE"  # 0 disables every native kernel
FLAGS = ["-O3", "-fPIC", "-shared", "-fopenmp", "-fno-fast-math", "-ffp-contract=off"]


def cache_dir() -> Path:
    """Where built kernels live: $REPAINT_NERF_CACHE/native, else ~/.cache/repaint-nerf/native."""
    root = os.environ.get("REPAINT_NERF_CACHE") or os.path.join(os.path.expanduser("~"), ".cache", "repaint-nerf")
    return Path(root) / "native"


def build(source: Path) -> Path:
    """Compile `source` into the cache (once per source hash) and return the shared library's path."""
    src = source.read_bytes()
    key = hashlib.sha1(src + " ".join(FLAGS).encode() + platform.machine().encode()).hexdigest()[:16]
    out = cache_dir() / f"{source.stem}-{key}.so"
    if out.exists():
        return out
    cc = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")
    if cc is None:
        raise RuntimeError("no C compiler found (install gcc, e.g. apt install build-essential)")
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{source.stem}-", suffix=".so", dir=out.parent)
    os.close(fd)
    try:
        proc = subprocess.run([cc, *FLAGS, str(source), "-o", tmp, "-lm"], capture_output=True, text=True)
        if proc.returncode != 0:
            raise RuntimeError(f"{cc} failed: {proc.stderr.strip()[-800:]}")
        os.replace(tmp, out)  # atomic: concurrent builders never load a half-written library
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return out


class NativeLibrary:
    """One kernel source, loaded on first `get()`; `failed` says why it is unavailable (then `get()` is None)."""

    def __init__(self, source: Path, bind: Callable[[ctypes.CDLL], ctypes.CDLL], what: str):
        self.source, self.bind, self.what = source, bind, what
        self.lib: ctypes.CDLL | None = None
        self.failed: str | None = None
        self._lock = threading.Lock()

    def get(self) -> ctypes.CDLL | None:
        """The loaded library, building it on first use; None (after one warning) when it cannot be built."""
        if self.lib is not None or self.failed is not None:
            return self.lib
        with self._lock:
            if self.lib is None and self.failed is None:
                if os.environ.get(ENV_NATIVE, "1") == "0":
                    self.failed = f"${ENV_NATIVE}=0"
                    return None
                try:
                    self.lib = self.bind(ctypes.CDLL(str(build(self.source))))
                except Exception as exc:  # noqa: BLE001 - any build or load failure means: use the PyTorch path
                    self.failed = f"{type(exc).__name__}: {exc}"
                    warnings.warn(f"native {self.what} kernel unavailable ({self.failed}); using the slower "
                                  f"PyTorch path", RuntimeWarning, stacklevel=3)
        return self.lib
