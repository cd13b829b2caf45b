"""Copy a capture out of a fetched snapshot (a git directory, read with `git ls-tree` / `git cat-file`) or a plain
folder into a local capture folder, byte for byte as the repository ships it (issue 32: "opens without edits"),
and optionally add shrunk copies of its images as `images_N/` (the LLFF / nerfstudio convention) beside them.

Blobs a snapshot lists but lacks, and Git LFS pointers standing in for files, are not copied and are reported, so
the folder holds exactly what the snapshot really has. A `.capture.json` beside the files records the source.
"""
from __future__ import annotations

import json
import shutil
import subprocess
from dataclasses import dataclass, field
from pathlib import Path

from repaint_nerf.core.bench.captures import Capture
from repaint_nerf.core.errors import UserError

LFS_PREFIX = b"version https://git-lfs.github.com/spec/"
SOURCE_FILE = ".capture.json"
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")


@dataclass
class Prepared:
    """What a preparation wrote: the folder, files copied, files the source lacked, shrunk copies made."""

    folder: Path
    copied: int = 0
    missing: list[str] = field(default_factory=list)  # paths inside the capture
    shrunk: dict[int, int] = field(default_factory=dict)  # factor -> images written

    def to_dict(self) -> dict:
        return {"folder": str(self.folder), "copied": self.copied, "missing": self.missing,
                "shrunk": {str(k): v for k, v in self.shrunk.items()}}


def is_git_dir(path: Path) -> bool:
    """Whether `path` is a git directory (a bare snapshot such as /work/.mirror/OWNER+NAME/repo, or a .git)."""
    return (path / "HEAD").is_file() and (path / "objects").is_dir()


def _git(git_dir: Path, *args: str, data: bytes | None = None) -> bytes:
    r = subprocess.run(["git", f"--git-dir={git_dir}", *args], input=data, capture_output=True)
    if r.returncode != 0:
        raise UserError(f"git {' '.join(args[:2])} failed in {git_dir}: {r.stderr.decode(errors='replace').strip()}",
                        hint="give the snapshot's git directory (e.g. /work/.mirror/OWNER+NAME/repo)")
    return r.stdout


def tree_entries(git_dir: Path, commit: str, inside: str) -> list[tuple[str, str, str]]:
    """(mode, object id, path relative to `inside`) of every file under `inside` at `commit`."""
    spec = inside.strip("/")
    out = _git(git_dir, "ls-tree", "-r", "-z", commit, "--", spec or ".")
    entries = []
    for rec in out.split(b"\0"):
        if not rec:
            continue
        meta, path = rec.decode().split("\t", 1)
        mode, kind, oid = meta.split()
        if kind != "blob":
            continue  # a submodule: nothing to copy
        rel = path[len(spec) + 1:] if spec else path
        entries.append((mode, oid, rel))
    if not entries:
        raise UserError(f"nothing under {spec or 'the root'!r} at {commit[:12]} in {git_dir}",
                        hint="check --path and that the snapshot is of the registered repository")
    return entries


def _present(git_dir: Path, oids: list[str]) -> set[str]:
    """The object ids the snapshot really holds (a snapshot may list large files it lacks)."""
    out = _git(git_dir, "cat-file", "--batch-check", data="".join(o + "\n" for o in oids).encode())
    return {ln.split()[0] for ln in out.decode().splitlines() if ln and not ln.endswith(" missing")}


def copy_from_git(git_dir: Path, commit: str, inside: str, dest: Path) -> Prepared:
    """Write the files under `inside` at `commit` into `dest`, leaving out absent blobs, LFS pointers and links."""
    if subprocess.run(["git", f"--git-dir={git_dir}", "cat-file", "-e", f"{commit}^{{commit}}"],
                      capture_output=True).returncode != 0:
        raise UserError(f"the snapshot in {git_dir} does not hold commit {commit}",
                        hint="fetch the repository again, or give --commit HEAD to take the snapshot's newest")
    entries = tree_entries(git_dir, commit, inside)
    present = _present(git_dir, [oid for _, oid, _ in entries])
    res = Prepared(dest)
    for mode, oid, rel in entries:
        if mode == "120000" or oid not in present:
            res.missing.append(rel)
            continue
        data = _git(git_dir, "cat-file", "blob", oid)
        if data.startswith(LFS_PREFIX):
            res.missing.append(rel)
            continue
        target = dest / rel
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(data)
        res.copied += 1
    return res


def copy_from_folder(src: Path, dest: Path) -> Prepared:
    """Copy a plain folder (a capture already on disk) into `dest` as it is."""
    shutil.copytree(src, dest, symlinks=False)
    return Prepared(dest, copied=sum(1 for p in dest.rglob("*") if p.is_file()))


def shrink_images(folder: Path, factor: int) -> int:
    """Write `images_N/` beside `images/`: each image shrunk by `factor` (area filter), same name and format; an
    `images_N/` the capture already ships is kept as it is. Returns the images written."""
    import cv2

    src, out = folder / "images", folder / f"images_{factor}"
    if not src.is_dir() or out.exists():
        return 0
    out.mkdir()
    n = 0
    for p in sorted(src.iterdir()):
        if p.suffix.lower() not in IMAGE_SUFFIXES:
            continue
        img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        if img is None:
            continue
        h, w = img.shape[:2]
        small = cv2.resize(img, (max(1, round(w / factor)), max(1, round(h / factor))), interpolation=cv2.INTER_AREA)
        cv2.imwrite(str(out / p.name), small)
        n += 1
    return n


def prepare(cap: Capture, source: Path, dest_root: Path, commit: str | None = None, shrink: tuple[int, ...] = (),
            force: bool = False) -> Prepared:
    """Copy capture `cap` from `source` (a git directory, or a plain folder holding it or its repository) into
    `dest_root/NAME`, add `images_N/` copies for each factor in `shrink`, and write `.capture.json`."""
    source = Path(source).expanduser()
    dest = Path(dest_root).expanduser() / cap.name
    if not source.exists():
        raise UserError(f"--from {source}: no such file or folder",
                        hint=f"fetch github:{cap.repo} first and give its git directory")
    if dest.exists():
        if not force:
            raise UserError(f"{dest} already exists", hint="use it as it is, or add --force to prepare it again")
        shutil.rmtree(dest)
    if any(f < 2 for f in shrink):
        raise UserError(f"--shrink factors must be whole numbers >= 2, got {list(shrink)}", hint="e.g. --shrink 4,8")
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = dest.with_name(dest.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    if is_git_dir(source):
        rev = commit or cap.commit
        res = copy_from_git(source, rev, cap.path, tmp)
        origin = {"git_dir": str(source), "commit": _git(source, "rev-parse", f"{rev}^{{commit}}").decode().strip()}
    else:
        folder = source / cap.path if cap.path and (source / cap.path).is_dir() else source
        res = copy_from_folder(folder, tmp)
        origin = {"folder": str(folder)}
    for f in shrink:
        res.shrunk[f] = shrink_images(tmp, f)
    (tmp / SOURCE_FILE).write_text(json.dumps({"capture": cap.to_dict(), "source": origin, **res.to_dict(),
                                               "folder": str(dest)}, indent=2))
    tmp.rename(dest)
    res.folder = dest
    return res
