"""A damaged workspace is repaired, not thrown away (issue 36).

Every kind of damage (a truncated file, flipped bytes, a missing file, an empty file, a file from another
workspace, settings of an older format) is refused on open with a message that names the file and offers
`repaint-nerf repair`, and `repair` brings back every version that was whole. `kill -9` at seeded random points
of training, of a Repaint and of a save (forked children of this process, so no interpreter start per kill)
loses no version whose save had returned. A full disk and a read-only folder fail with a message and change
nothing. Each test counts the versions kept against the versions complete before the damage; the table goes to
tests/artifacts/workspace_repair.json.
"""
from __future__ import annotations

import contextlib
import errno
import json
import os
import random
import shutil
import signal
import subprocess
import time
import traceback
from pathlib import Path

import numpy as np
import pytest
import torch

from repaint_nerf.core.errors import SaveFailed, UserError, WorkspaceDamaged
from repaint_nerf.core.train.checkpoint import Checkpoint
from repaint_nerf.core.workspace import atomic, integrity
from repaint_nerf.core.workspace.repair import repair_workspace
from repaint_nerf.core.workspace.workspace import VersionInfo, Workspace
from small_workspace import Base, small_workspace

TABLE: dict[str, list] = {"damage": [], "kill": []}


@pytest.fixture(scope="module")
def base(scene_factory, tmp_path_factory) -> Base:
    torch.set_num_threads(1)
    return small_workspace(scene_factory("demo", size=16, views=4, test_views=1),
                           tmp_path_factory.mktemp("repair") / "ws")


# -- what a user sees --------------------------------------------------------------------------------------
def open_all(root: Path) -> str:
    """Open the workspace as the editor and commands do and step through every version (undo/redo reads each):
    'opens', or the first line of the refusal."""
    from repaint_nerf.core.select.masks import load_masks
    from repaint_nerf.core.select.selection import Selection

    try:
        ws = Workspace.open(root)
        ws.settings
        if (ws.checkpoints_dir / "stage1.safetensors").exists():  # what training resumes from
            Checkpoint.load(ws.checkpoints_dir / "stage1.safetensors")
        for info in ws.versions:
            Checkpoint.load(ws.version_path(info))
        if (ws.selections_dir / "current.json").exists():
            Selection.load(ws)
        if (ws.masks_dir / "index.json").exists() or any(ws.masks_dir.glob("*.png")):
            load_masks(ws.masks_dir)
    except UserError as exc:
        return str(exc)
    return "opens"


def _bytes_of_versions(root: Path) -> dict[str, bytes]:
    idx = json.loads((root / "versions" / "index.json").read_text())
    return {vid: (root / info["file"]).read_bytes() for vid, info in idx["versions"].items()}


def _kept(root: Path, before: dict[str, bytes]) -> int:
    """Versions of `before` that the workspace lists and whose file is byte for byte what it was."""
    ws = Workspace.open(root)
    listed = {v: ws.version_path(VersionInfo(**info)) for v, info in ws._index()["versions"].items()}
    return sum(1 for vid, data in before.items() if vid in listed and listed[vid].read_bytes() == data)


# -- the damage kinds --------------------------------------------------------------------------------------
def truncate(p: Path, base: Base) -> None:
    p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])


def flip(p: Path, base: Base) -> None:
    """Change bytes so the file still parses: a digit in a JSON file, bits deep in a binary file's data."""
    data = bytearray(p.read_bytes())
    if p.suffix == ".json":
        i = max(i for i, c in enumerate(data) if chr(c).isdigit() and i < len(data) - 80)
        data[i] = ord("7" if data[i] != ord("7") else "3")
    else:
        for i in (len(data) - 5, len(data) - len(data) // 3):
            data[i] ^= 0x5A
    p.write_bytes(bytes(data))


def remove(p: Path, base: Base) -> None:
    p.unlink()


def empty(p: Path, base: Base) -> None:
    p.write_bytes(b"")


def foreign(p: Path, base: Base) -> None:
    """The same-named file of another workspace (a whole, valid file: only its identity is wrong)."""
    shutil.copyfile(base.other / p.relative_to(p.parents[1]), p)


def foreign_unindexed(p: Path, base: Base) -> None:
    """A file of another workspace and no index to tell it by: only the file's own stamp can."""
    foreign(p, base)
    (p.parent / "index.json").unlink()


def older_settings(p: Path, base: Base) -> None:
    """settings.json as an older program wrote it: model paths in a nested 'models' map, no scene entry."""
    p.write_text(json.dumps({"models": {"sd": "/models/sd-2-base", "clip": "/models/clip"}, "downscale": 1.0}))


def first_teacher_cache(root: Path) -> Path:
    return sorted((root / "teachers").glob("*/*/*.safetensors"))[0]


CASES = [
    ("truncated", "versions/v0003.safetensors", truncate),
    ("truncated", "versions/index.json", truncate),
    ("truncated", "settings.json", truncate),
    ("truncated", "checkpoints/stage1.safetensors", truncate),
    ("flipped bytes", "versions/v0002.safetensors", flip),
    ("flipped bytes", "versions/index.json", flip),
    ("flipped bytes", "selections/current.json", flip),
    ("flipped bytes", "masks/mask_0001.png", flip),
    ("flipped bytes", "teachers cache", flip),
    ("missing", "versions/v0003.safetensors", remove),
    ("missing", "versions/index.json", remove),
    ("missing", "workspace.json", remove),
    ("missing", "settings.json", remove),
    ("missing", "masks/index.json", remove),
    ("empty", "versions/v0001.safetensors", empty),
    ("empty", "workspace.json", empty),
    ("empty", "selections/current.json", empty),
    ("from another workspace", "versions/v0002.safetensors", foreign),
    ("from another workspace, index lost", "versions/v0002.safetensors", foreign_unindexed),
    ("older format", "settings.json", older_settings),
]


@pytest.mark.timeout(120)
@pytest.mark.parametrize("kind,target,damage", CASES, ids=[f"{k}:{t}" for k, t, _ in CASES])
def test_repair_brings_back_every_whole_version(base, tmp_path, kind, target, damage):
    """Damage one file of a copy of the workspace: opening refuses it (naming the file and offering repair, or
    opens when nothing it uses is damaged), `repair` fixes it, the workspace then opens, a second repair finds
    nothing to do, every version that was whole is kept byte for byte and the damaged one is set aside."""
    root = tmp_path / "ws"
    shutil.copytree(base.root, root)
    before = _bytes_of_versions(root)
    path = first_teacher_cache(root) if target == "teachers cache" else root / target
    damage(path, base)
    whole = {v: d for v, d in before.items() if target != f"versions/{v}.safetensors"}
    message = open_all(root)
    if message != "opens":
        assert str(root) in message and ("repair" in message or "select again" in message), message
    actions = repair_workspace(root)
    assert actions, "repair did nothing about the damage"
    assert open_all(root) == "opens"
    assert repair_workspace(root) == [], "a repaired workspace is healthy"
    kept = _kept(root, whole)
    assert kept == len(whole)
    if kind != "older format":
        assert any((root / "damaged").rglob("*")) or damage is remove
    if target == "settings.json" and damage is not older_settings:
        assert Workspace.open(root).settings["scene"] == str(Path(base.scene.root))
    if damage is older_settings:
        settings = Workspace.open(root).settings
        assert settings["sd_path"] == "/models/sd-2-base" and "models" not in settings and settings["scene"]
    if "masks" in target:
        from repaint_nerf.core.select.masks import load_masks

        assert len(load_masks(root / "masks")) == len(base.masks)
    TABLE["damage"].append({"damage": kind, "file": target, "message": message.splitlines()[0][len(str(root)) + 1:]
                            if message != "opens" else "opens (nothing it reads is damaged)",
                            "repaired": True, "actions": len(actions),
                            "versions_kept": kept, "versions_whole_before": len(whole),
                            "versions_before": len(before)})


def test_a_damaged_version_is_refused_with_its_name_and_repair(base, tmp_path):
    """Opening the current version of a workspace whose current file is altered: a WorkspaceDamaged naming the
    version file and the exact repair command; the file is never read into a field."""
    from repaint_nerf.core.session import open_trained

    root = tmp_path / "ws"
    shutil.copytree(base.root, root)
    flip(root / "versions" / "v0003.safetensors", base)
    with pytest.raises(WorkspaceDamaged) as exc:
        open_trained(root, "cpu")
    text = str(exc.value)
    assert "v0003.safetensors" in text and f"repaint-nerf repair {root}" in text and "content hash" in text
    assert exc.value.workspace == root


def test_cli_repair_prints_one_line_per_action_and_nothing_when_healthy(base, tmp_path, capsys):
    from repaint_nerf.app.cli import main

    root = tmp_path / "ws"
    shutil.copytree(base.root, root)
    assert main(["repair", str(root)]) == 0
    assert capsys.readouterr().out == ""
    truncate(root / "versions" / "v0003.safetensors", base)
    remove(root / "versions" / "index.json", base)
    assert main(["repair", str(root)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 2 and "v0003" in lines[0] and "damaged/versions/v0003" in lines[0]
    assert "index.json: rebuilt over 2 good version(s), current v0002" in lines[1]


@pytest.fixture(scope="module", autouse=True)
def write_table(artifacts_dir):
    """The damage x (message, repaired, versions kept) table, for the issue's note."""
    yield
    (artifacts_dir / "workspace_repair.json").write_text(json.dumps(TABLE, indent=1))


# -- kill -9 at seeded random points ----------------------------------------------------------------------
def _arm_kill(n: int) -> None:
    """SIGKILL this process at its n-th file-system step of a save: a sealed safetensors file written but not yet
    sealed, a temporary file about to be synced, a rename about to happen, a folder about to be synced."""
    count = [0]

    def step(real):
        def wrapped(*args):
            count[0] += 1
            if count[0] == n:
                os.kill(os.getpid(), signal.SIGKILL)
            return real(*args)
        return wrapped

    os.fsync, os.replace = step(os.fsync), step(os.replace)
    integrity.seal_file = step(integrity.seal_file)


def _phase_training(base: Base, ws: Workspace, saved) -> None:
    """Stage 1 as the editor runs it: train, save the training checkpoint, save a reconstruction version."""
    tr = base.trainer
    tr.workspace = ws
    while True:
        tr.train(steps=tr.step_count + 1)
        tr.save_checkpoint()
        saved(tr.save_version("reconstruction"))


def _phase_repaint(base: Base, ws: Workspace, saved) -> None:
    """Repaints that finish and save themselves as edit versions."""
    from repaint_nerf.core.repaint.trainer import RepaintTrainer

    while True:
        rp = RepaintTrainer(base.scene, base.trainer.field, base.trainer.grid, workspace=ws, masks=base.masks,
                            guidance="recolor", prompt="a green box", steps=2, resolution=16, max_samples=32,
                            snapshot_every=0, region_resolution=16)
        rp.run()
        saved(rp.version)


def _phase_save(base: Base, ws: Workspace, saved) -> None:
    """Saving the project: settings, the selection, its masks, a version, undo and redo (index writes)."""
    from repaint_nerf.core.select.masks import write_masks
    from repaint_nerf.core.select.selection import Selection

    sel, ck, i = Selection.load(ws), base.trainer.checkpoint(), 0
    while True:
        i += 1
        ws.update_settings(saves=i)
        sel.save(ws)
        masks = [~m for m in base.masks] if i % 2 else base.masks  # new content: a torn write shows
        write_masks(ws.masks_dir, masks, list(base.scene.train.names))
        saved(ws.save_version(f"save {i}", ck))
        ws.undo()
        ws.redo()


PHASES = {"training": _phase_training, "repaint": _phase_repaint, "save": _phase_save}


def _killed_run(base: Base, root: Path, phase: str, at_step: int | None, delay: float | None) -> dict[str, str]:
    """Run `phase` on `root` in a forked child until it is SIGKILLed (at its `at_step`-th save step, or by this
    process after `delay` s); returns the versions whose save returned before the kill (id -> content hash)."""
    log, err = root.parent / "saved.log", root.parent / "child.err"
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: never returns into pytest
        code = 0
        try:
            os.close(r)
            torch.set_num_threads(1)
            ws = Workspace.open(root)
            with open(log, "a") as out:
                def saved(info):
                    out.write(f"{info.id} {info.sha256}\n")
                    out.flush()  # in the kernel's page cache: survives the SIGKILL of this process
                if at_step is not None:
                    _arm_kill(at_step)
                os.write(w, b"1")
                PHASES[phase](base, ws, saved)
        except BaseException:
            err.write_text(traceback.format_exc())
            code = 1
        finally:
            os._exit(code)
    os.close(w)
    os.read(r, 1)
    os.close(r)
    if delay is not None:
        time.sleep(delay)
        os.kill(pid, signal.SIGKILL)
    deadline = time.monotonic() + 60
    while (done := os.waitpid(pid, os.WNOHANG))[0] == 0:
        if time.monotonic() > deadline:  # e.g. a lock held by another thread at the fork: fail, do not hang
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            pytest.fail(f"the {phase} child never reached save step {at_step}")
        time.sleep(0.005)
    status = done[1]
    assert os.WIFSIGNALED(status) and os.WTERMSIG(status) == signal.SIGKILL, \
        err.read_text() if err.exists() else status
    return dict(line.split() for line in log.read_text().splitlines()) if log.exists() else {}


def _versions_kept(root: Path, complete: dict[str, str]) -> int:
    """How many of the `complete` versions the workspace lists and reads back with their saved content hash."""
    try:
        ws = Workspace.open(root)
        index = ws._index()["versions"]
    except UserError:
        return 0
    kept = 0
    for vid, digest in complete.items():
        try:
            info = VersionInfo(**index[vid])
            Checkpoint.load(ws.version_path(info))
            kept += info.sha256 == digest
        except (KeyError, UserError):
            pass
    return kept


def _kill_points() -> list[tuple[str, int | None, float | None]]:
    """24 kill points, seeded: per phase 5 at a random save step (1-30) and 3 at a random moment (0.05-1.2 s)."""
    rng = random.Random(36)
    points = []
    for phase in PHASES:
        points += [(phase, rng.randint(1, 30), None) for _ in range(5)]
        points += [(phase, None, round(rng.uniform(0.05, 1.2), 3)) for _ in range(3)]
    return points


@pytest.mark.timeout(300)
def test_kill_9_anywhere_loses_no_complete_version(base, tmp_path):
    """SIGKILL at 24 seeded points of training, of a Repaint and of a save: afterwards the workspace opens, or
    `repair` makes it open, with every version whose save had returned (and every one from before) kept whole."""
    before = {v.id: v.sha256 for v in Workspace.open(base.root).versions}
    for k, (phase, at_step, delay) in enumerate(_kill_points()):
        root = tmp_path / f"kill{k}" / "ws"
        shutil.copytree(base.root, root)
        complete = {**before, **_killed_run(base, root, phase, at_step, delay)}
        opened = open_all(root)
        actions = [] if opened == "opens" and _versions_kept(root, complete) == len(complete) \
            else repair_workspace(root)
        assert open_all(root) == "opens", (phase, at_step, delay, actions)
        kept = _versions_kept(root, complete)
        TABLE["kill"].append({"phase": phase, "kill": f"save step {at_step}" if at_step else f"after {delay} s",
                              "opened": opened == "opens", "message": opened.splitlines()[0][len(str(root)) + 1:]
                              if opened != "opens" else "", "repair_actions": len(actions),
                              "versions_kept": kept, "versions_complete_before": len(complete)})
        assert kept == len(complete), (phase, at_step, delay, kept, complete, actions)
    kept = sum(r["versions_kept"] for r in TABLE["kill"])
    total = sum(r["versions_complete_before"] for r in TABLE["kill"])
    print(f"kill -9 at {len(TABLE['kill'])} points: {kept}/{total} complete versions kept")
    assert kept == total


# -- a full disk, a read-only folder ----------------------------------------------------------------------
@contextlib.contextmanager
def _small_disk(folder: Path, size_kb: int):
    """A tmpfs of `size_kb` mounted at `folder` when this process may mount (root), else a plain folder; yields
    whether it is the real small disk."""
    folder.mkdir(parents=True)
    real = os.geteuid() == 0 and subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={size_kb}k", "tmpfs", str(folder)], capture_output=True).returncode == 0
    try:
        yield real
    finally:
        if real:
            subprocess.run(["umount", "-l", str(folder)], capture_output=True)


def _refuse(monkeypatch, code: int) -> None:
    """Where no small disk can be mounted: the file system refuses every new file with `code`."""
    def refused(*args, **kwargs):
        raise OSError(code, os.strerror(code))

    monkeypatch.setattr(atomic.tempfile, "mkstemp", refused)


def _state(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_full_disk_fails_with_a_message_and_keeps_the_previous_state(base, tmp_path, monkeypatch):
    """Versions saved onto a small disk until it is full: the save that does not fit is a SaveFailed saying the
    disk is full, and every file is as before it (no partial version, no temporary file, the index unchanged)."""
    ck = base.trainer.checkpoint()
    size = len(ck.tensors) and sum(t.numel() * t.element_size() for t in ck.tensors.values())
    with _small_disk(tmp_path / "disk", int(2.5 * size) // 1024 + 64) as real:
        ws = Workspace.create(tmp_path / "disk" / "ws", {"scene": str(base.scene.root)})
        ws.save_version("first", ck, kind="stage1")
        if not real:
            _refuse(monkeypatch, errno.ENOSPC)
        for i in range(20):
            state = _state(ws.root)
            try:
                ws.save_version(f"edit {i}", ck)
            except SaveFailed as exc:
                failed = exc
                break
        else:
            pytest.fail("the small disk never filled up")
        assert failed.errno == errno.ENOSPC and "the disk is full" in str(failed) and "unchanged" in str(failed)
        assert _state(ws.root) == state
        monkeypatch.undo()
        assert open_all(ws.root) == "opens" and repair_workspace(ws.root) == []
        TABLE.setdefault("disk", []).append({"case": "full disk", "how": "tmpfs" if real else "simulated ENOSPC",
                                             "message": str(failed).splitlines()[0].split(": ", 1)[1],
                                             "versions_kept": len(ws.versions), "versions_before": len(ws.versions)})


def test_read_only_folder_fails_with_a_message_and_still_opens(base, tmp_path, monkeypatch):
    """A workspace whose folder became read-only: saving is a SaveFailed saying so, nothing changes, and the
    workspace still opens and reads its versions (opening writes nothing)."""
    ck = base.trainer.checkpoint()
    with _small_disk(tmp_path / "disk", 4096) as real:
        ws = Workspace.create(tmp_path / "disk" / "ws", {"scene": str(base.scene.root)})
        ws.save_version("first", ck, kind="stage1")
        state = _state(ws.root)
        if real:
            subprocess.run(["mount", "-o", "remount,ro", str(tmp_path / "disk")], check=True)
        elif os.geteuid() != 0:
            for d in [ws.root, *(p for p in ws.root.rglob("*") if p.is_dir())]:
                d.chmod(0o555)
        else:
            _refuse(monkeypatch, errno.EROFS)
        try:
            with pytest.raises(SaveFailed) as exc:
                ws.save_version("second", ck)
            with pytest.raises(SaveFailed):
                ws.update_settings(threshold=0.4)
            text = str(exc.value)
            assert "read-only" in text or "not writable" in text
            assert _state(ws.root) == state
            opened = Workspace.open(ws.root)
            Checkpoint.load(opened.version_path(opened.current_version))
        finally:
            for d in [ws.root, *(p for p in ws.root.rglob("*") if p.is_dir())] if not real else ():
                d.chmod(0o755)
        TABLE.setdefault("disk", []).append({"case": "read-only folder", "how": "tmpfs remounted read-only" if real
                                             else "simulated", "message": text.splitlines()[0].split(": ", 1)[1],
                                             "versions_kept": 1, "versions_before": 1})


def test_an_unchanged_version_opens_without_hashing_and_a_rewrite_is_hashed(base, tmp_path, monkeypatch):
    """Opening reads a version's identity (size, times, inode) recorded at save: unchanged, its content hash is
    not recomputed; rewritten, even with the modification time put back, it is hashed and refused."""
    root = tmp_path / "ws"
    ws = Workspace.create(root, {"scene": str(base.scene.root)})
    info = ws.save_version("reconstruction", base.trainer.checkpoint(), kind="stage1")
    hashed = []
    real = integrity._digest
    monkeypatch.setattr(integrity, "_digest", lambda *a: hashed.append(1) or real(*a))
    monkeypatch.setattr(integrity, "_CHECKED", {})  # a new process: nothing checked yet
    path = Workspace.open(root).version_path(info)
    Checkpoint.load(path)
    assert hashed == []
    st = os.stat(path)
    flip(path, base)
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))
    with pytest.raises(WorkspaceDamaged, match="content hash"):
        Checkpoint.load(Workspace.open(root).version_path(info))
    assert hashed


def test_repair_leaves_a_newer_programs_workspace_alone(base, tmp_path):
    """A version of a newer header format is not damage: repair refuses and moves nothing."""
    from safetensors.torch import save_file

    root = tmp_path / "ws"
    shutil.copytree(base.root, root)
    newer = root / "versions" / "v0009.safetensors"
    save_file({"w": torch.ones(2)}, str(newer), metadata={"repaint_nerf": json.dumps({"format": 99})})
    with pytest.raises(UserError, match="newer repaint-nerf"):
        repair_workspace(root)
    assert newer.exists() and not (root / "damaged").exists()
