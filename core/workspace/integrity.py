"""Content hashes that make every workspace file checkable (the way safetensors checks a header before any
tensor, and git names objects by their hash).

A safetensors file is *sealed*: its metadata holds `SEAL_KEY`, the SHA-256 of the whole file with that value
written as 64 zeros, so the file checks itself with no index (the digest is patched into place in the
temporary file before the atomic rename). A JSON file (the version index, a selection, the masks index) is
sealed by a last `"sha256"` field: the hash of its text with that value blanked. Files written before the seals
existed carry none: they read as before (`None` from the checks), and only a seal that does not match is
damage.

Hashing is the slow part (SHA-256 runs at ~1.5 GB/s here), so, like git's index, a file checked once (or saved)
is remembered with its size, times, inode and device: while those are unchanged nothing rewrote it, and reading
it again skips the hash. A workspace records that identity in its version index at save time, so opening an
unchanged version costs a `stat`, and any rewrite (a truncation, flipped bytes, a foreign copy; even one that
restores the modification time, as the change time moves) is hashed and refused. Bytes that change with no
file-system write at all (media decay) are found by `repaint-nerf repair`, which hashes everything.
"""
from __future__ import annotations

import hashlib
import json
import os
import struct
from pathlib import Path
from typing import Any, BinaryIO

SEAL_KEY = "repaint_nerf_sha256"
JSON_SEAL = "sha256"
STAMP_KEY = "repaint_nerf_version"  # a workspace version's identity (core.workspace.workspace.save_version)
_BLANK = b"0" * 64
_NEEDLE = f'"{SEAL_KEY}":"'.encode()
_JSON_NEEDLE = f'"{JSON_SEAL}": "'
_MAX_HEADER = 100 * 2**20  # safetensors' own limit on the JSON header
_CHUNK = 2**20
_CHECKED: dict[str, tuple[tuple[int, ...], str | None]] = {}  # abspath -> (stat identity, digest) of this process
BOOK = ".checked.json"  # per folder: {file name: stat identity + [digest]} of the sealed files written there


class IntegrityError(Exception):
    """A file whose bytes are not the ones written: empty, truncated, altered, or not a sealed file at all."""


def sealed_metadata(metadata: dict[str, str] | None = None) -> dict[str, str]:
    """`metadata` plus a blank seal, for a safetensors writer whose output `seal_file` / `seal_bytes` then seals."""
    return {**(metadata or {}), SEAL_KEY: _BLANK.decode()}


def _read_header(f: BinaryIO) -> bytes:
    """The 8-byte length and the JSON header of a safetensors file (IntegrityError when they are not there)."""
    head = f.read(8)
    if not head:
        raise IntegrityError("the file is empty")
    if len(head) < 8:
        raise IntegrityError("the file is truncated (no complete header)")
    (n,) = struct.unpack("<Q", head)
    if n > _MAX_HEADER:
        raise IntegrityError("the file is not a safetensors file (its header length is impossible)")
    body = f.read(n)
    if len(body) < n:
        raise IntegrityError("the file is truncated (inside its header)")
    return head + body


def _seal_at(header: bytes) -> int | None:
    """Offset of the 64 hex digits of the seal in the file, or None for an unsealed file."""
    i = header.find(_NEEDLE)
    return None if i < 0 else i + len(_NEEDLE)


def _digest(header: bytes, at: int, rest: BinaryIO | bytes) -> str:
    """SHA-256 of the header with the seal blanked, then of `rest` (a file read to its end, or bytes)."""
    h = hashlib.sha256(header[:at])
    h.update(_BLANK)
    h.update(header[at + 64:])
    if isinstance(rest, (bytes, bytearray, memoryview)):
        h.update(rest)
    else:
        buf = bytearray(_CHUNK)
        view = memoryview(buf)
        while n := rest.readinto(buf):
            h.update(view[:n])
    return h.hexdigest()


def seal_file(path: str | Path) -> str:
    """Write the seal of a safetensors file written with `sealed_metadata` into it; returns the digest."""
    with open(path, "r+b") as f:
        header = _read_header(f)
        at = _seal_at(header)
        if at is None:
            raise ValueError(f"{path} was not written with sealed_metadata()")
        digest = _digest(header, at, f)
        f.seek(at)
        f.write(digest.encode())
    return digest


def seal_bytes(data: bytes) -> bytes:
    """The sealed form of a safetensors file's bytes written with `sealed_metadata` (e.g. by safetensors' `save`)."""
    from io import BytesIO

    header = _read_header(BytesIO(data))
    at = _seal_at(header)
    if at is None:
        raise ValueError("these bytes were not written with sealed_metadata()")
    digest = _digest(header, at, memoryview(data)[len(header):])
    return data[:at] + digest.encode() + data[at + 64:]


def stored_digest(path: str | Path) -> str | None:
    """The seal a safetensors file says it has (its header only: microseconds); None when it has none."""
    with open(path, "rb") as f:
        header = _read_header(f)
    at = _seal_at(header)
    return None if at is None else header[at:at + 64].decode("ascii", "replace")


def stat_key(path: str | Path) -> list[int]:
    """What changes whenever a file is rewritten: size, modification and change times (ns), inode, device."""
    st = os.stat(path)
    return [st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino, st.st_dev]


def remember(path: str | Path, key: list[int], digest: str | None) -> None:
    """Record that `path`, as identified by `key`, holds the content whose seal is `digest` (saved or checked)."""
    _CHECKED[os.path.abspath(path)] = (tuple(key), digest)


def record(path: str | Path, digest: str | None) -> None:
    """After a sealed file is in place: remember it, and note its identity in its folder's book, so the next
    process reads it without hashing while nothing rewrites it. The book is a cache: failing to write it, or
    a damaged one, only means a hash later."""
    path = Path(path)
    key = stat_key(path)
    remember(path, key, digest)
    book = path.parent / BOOK
    entries = _read_book(book)
    entries[path.name] = key + [digest]
    tmp = book.with_name(f"{BOOK}.{os.getpid()}.tmp")
    try:
        tmp.write_text(json.dumps(entries), encoding="utf-8")
        os.replace(tmp, book)
    except OSError:
        try:
            tmp.unlink()
        except OSError:
            pass


def _read_book(book: Path) -> dict:
    try:
        entries = json.loads(book.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    return entries if isinstance(entries, dict) else {}


def _booked(path: str | Path, key: list[int]) -> tuple[bool, str | None]:
    """(True, digest) when the folder's book holds `path` with the identity `key`."""
    entry = _read_book(Path(path).parent / BOOK).get(Path(path).name)
    if isinstance(entry, list) and len(entry) == len(key) + 1 and entry[:-1] == key:
        return True, entry[-1]
    return False, None


def trust(path: str | Path, key: list[int] | None, digest: str | None) -> bool:
    """Take the file as checked when its identity is still `key` (recorded when it was saved or last checked);
    False, and nothing remembered, when the file was rewritten since (or no identity was recorded)."""
    if not key or digest is None:
        return False
    try:
        now = stat_key(path)
    except OSError:
        return False
    if now != list(key):
        return False
    remember(path, now, digest)
    return True


def checked_key(path: str | Path, digest: str | None) -> list[int] | None:
    """The identity under which this process checked `path` to hold `digest`, if the file still has it."""
    hit = _CHECKED.get(os.path.abspath(path))
    if hit is None or hit[1] != digest or digest is None:
        return None
    try:
        return list(hit[0]) if stat_key(path) == list(hit[0]) else None
    except OSError:
        return None


def verify_file(path: str | Path, full: bool = False) -> str | None:
    """Hash the whole file and compare with its seal: the digest when it matches, None for an unsealed (older)
    file; an IntegrityError saying what is wrong otherwise. Costs one read at ~1.5 GB/s (SHA-256), skipped for
    a file this process saved or checked and nothing rewrote since (`full` hashes regardless: `repair`)."""
    key = stat_key(path)
    hit = _CHECKED.get(os.path.abspath(path))
    if not full and hit is not None and hit[0] == tuple(key):
        return hit[1]
    booked, digest = (False, None) if full else _booked(path, key)
    if booked:
        remember(path, key, digest)
        return digest
    with open(path, "rb") as f:
        header = _read_header(f)
        at = _seal_at(header)
        if at is None:
            return None
        stored = header[at:at + 64].decode("ascii", "replace")
        actual = _digest(header, at, f)
    if actual != stored:
        raise IntegrityError("its content hash does not match (the file is truncated or altered)")
    remember(path, key, stored)
    return stored


def read_metadata(path: str | Path) -> dict[str, str]:
    """The `__metadata__` of a safetensors file, from its header only (IntegrityError when unreadable)."""
    with open(path, "rb") as f:
        header = _read_header(f)
    try:
        meta = json.loads(header[8:]).get("__metadata__") or {}
    except (ValueError, AttributeError) as exc:
        raise IntegrityError("its header is not valid JSON") from exc
    return meta if isinstance(meta, dict) else {}


def read_stamp(path: str | Path) -> dict[str, Any] | None:
    """The version identity stamped into a workspace version file (None for a file without one)."""
    raw = read_metadata(path).get(STAMP_KEY)
    if raw is None:
        return None
    try:
        stamp = json.loads(raw)
    except ValueError as exc:
        raise IntegrityError("its version stamp is not valid JSON") from exc
    return stamp if isinstance(stamp, dict) else None


def sealed_json_text(obj: dict) -> str:
    """`obj` as indented JSON text sealed by a last `"sha256"` field: the SHA-256 of this very text with that
    value written as 64 zeros (hashing the text read back costs microseconds; re-serialising would cost more)."""
    body = {k: v for k, v in obj.items() if k != JSON_SEAL}
    text = json.dumps({**body, JSON_SEAL: _BLANK.decode()}, indent=2) + "\n"
    at = text.rindex(_JSON_NEEDLE) + len(_JSON_NEEDLE)
    return text[:at] + hashlib.sha256(text.encode()).hexdigest() + text[at + 64:]


def check_json_text(text: str, obj: Any) -> bool | None:
    """Whether JSON `text` (parsed: `obj`) matches its seal; None when it carries none (an older file). Any
    edit, re-serialisation included, makes it False."""
    if not isinstance(obj, dict) or JSON_SEAL not in obj:
        return None
    stored = str(obj[JSON_SEAL])
    at = text.rfind(_JSON_NEEDLE + stored)
    if at < 0 or len(stored) != 64:
        return False
    at += len(_JSON_NEEDLE)
    return hashlib.sha256((text[:at] + _BLANK.decode() + text[at + 64:]).encode()).hexdigest() == stored


def bytes_digest(data: bytes) -> str:
    """SHA-256 of raw bytes (a mask PNG's entry in the masks index)."""
    return hashlib.sha256(data).hexdigest()


def workspace_of(path: str | Path) -> Path | None:
    """The workspace folder holding `path` (the nearest parent with workspace.json), or None."""
    for parent in Path(path).resolve().parents:
        if (parent / "workspace.json").is_file():
            return parent
    return None


def repair_hint(path: str | Path, otherwise: str | None = None) -> str | None:
    """'run: repaint-nerf repair WS' for a file inside a workspace; `otherwise` for a file outside one."""
    ws = workspace_of(path)
    if ws is None:
        return otherwise
    return f"run: repaint-nerf repair {ws} (it sets damaged files aside and keeps every good version)"
