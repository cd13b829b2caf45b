"""Atomic file writes: a temporary file in the target's folder, fsync, then os.replace.

A crash or an exception midway leaves the previous file untouched and no temporary file behind,
so a workspace never holds a half-written checkpoint or settings file.
"""
from __future__ import annotations

import contextlib
import json
import os
import re
import tempfile
from pathlib import Path
from typing import IO, Any, Iterator


def _fsync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:  # e.g. Windows cannot open folders; the rename is still atomic there
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside `path`; on a clean exit it replaces `path`, on an error it is removed (a
    refusal by the file system, e.g. a full disk, is raised as a SaveFailed naming `path` and the cause)."""
    from repaint_nerf.core.errors import SaveFailed

    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as exc:
        raise SaveFailed(path, exc) from exc
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            tmp.unlink()
        if isinstance(exc, OSError) and not isinstance(exc, SaveFailed) and exc.errno is not None:
            raise SaveFailed(path, exc) from exc  # a full disk or read-only folder says so, not a bare errno
        raise
    _fsync_dir(path.parent)


@contextlib.contextmanager
def atomic_open(path: str | Path, mode: str = "wb") -> Iterator[IO[Any]]:
    """Open a temporary file for writing that becomes `path` only if the block finishes without error."""
    if mode not in ("wb", "w"):
        raise ValueError("atomic_open writes only ('wb' or 'w')")
    with atomic_path(path) as tmp:
        with open(tmp, mode, **({} if "b" in mode else {"encoding": "utf-8"})) as f:
            yield f
            f.flush()


def write_bytes(path: str | Path, data: bytes) -> None:
    """Atomically write `data` to `path`."""
    with atomic_open(path, "wb") as f:
        f.write(data)


def write_json(path: str | Path, obj: Any) -> None:
    """Atomically write `obj` as indented JSON (serialisation errors leave the old file intact)."""
    text = json.dumps(obj, indent=2, sort_keys=False)
    with atomic_open(path, "w") as f:
        f.write(text + "\n")


def write_sealed_json(path: str | Path, obj: dict) -> None:
    """Atomically write `obj` as indented JSON sealed with its content hash (integrity.sealed_json_text)."""
    from repaint_nerf.core.workspace import integrity

    text = integrity.sealed_json_text(obj)
    with atomic_open(path, "w") as f:
        f.write(text)


def write_safetensors(path: str | Path, tensors: dict, metadata: dict[str, str] | None = None) -> str:
    """Atomically write torch tensors (moved to CPU, made contiguous) as a sealed safetensors file (its content
    hash inside, core.workspace.integrity); returns that hash."""
    from safetensors import SafetensorError
    from safetensors.torch import save_file

    from repaint_nerf.core.workspace import integrity

    cpu = {k: v.detach().to("cpu").contiguous().clone() for k, v in tensors.items()}
    with atomic_path(path) as tmp:
        try:
            save_file(cpu, str(tmp), metadata=integrity.sealed_metadata(metadata))
        except SafetensorError as exc:  # its I/O errors (a full disk) name the OS error only in the text
            code = re.search(r"os error (\d+)", str(exc))
            if code is None:
                raise
            raise OSError(int(code.group(1)), os.strerror(int(code.group(1)))) from exc
        digest = integrity.seal_file(tmp)
    integrity.record(path, digest)
    return digest


def write_sealed(path: str | Path, data: bytes) -> None:
    """Atomically write safetensors bytes made with `integrity.sealed_metadata`, sealed (e.g. a teacher cache)."""
    from repaint_nerf.core.workspace import integrity

    write_bytes(path, integrity.seal_bytes(data))
    integrity.record(path, integrity.stored_digest(path))


def sweep_stale_temps(folder: str | Path, older_than_s: float = 300.0) -> list[Path]:
    """Remove temporary files left in `folder` by writes that were killed midway (SIGKILL, power loss), once
    they are older than `older_than_s` (a live write keeps touching its file). Returns what was removed."""
    import time

    folder = Path(folder)
    removed = []
    if not folder.is_dir():
        return removed
    now = time.time()
    for p in folder.glob(".*.tmp"):
        with contextlib.suppress(OSError):
            if p.is_file() and now - p.stat().st_mtime > older_than_s:
                p.unlink()
                removed.append(p)
    return removed
