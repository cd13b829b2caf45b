"""Nothing lost (issue 8): a process killed in the middle of a save leaves the last good checkpoint loadable,
killed saves leave no lasting debris, checkpoints carry a format version, the original reconstruction is
never overwritten by an edit, and a finished edit saves itself as a workspace version.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from repaint_nerf.core.errors import WorkspaceError
from repaint_nerf.core.train.checkpoint import CHECKPOINT_FORMAT, Checkpoint
from repaint_nerf.core.workspace import atomic
from repaint_nerf.core.workspace.workspace import Workspace

ROOT = Path(__file__).resolve().parents[1]

# Saves a ~32 MB checkpoint (every element = the save's number) to argv[1] in a loop, printing each number
# once its save returned; with argv[2] == "ws" it saves workspace versions instead.
_SAVER = r"""
import sys, torch
from repaint_nerf.core.train.checkpoint import Checkpoint
from repaint_nerf.core.workspace.workspace import Workspace
path, mode = sys.argv[1], sys.argv[2]
ws = Workspace.open_or_create(path) if mode == "ws" else None
i = 0
while True:
    i += 1
    t = torch.full((8_000_000,), float(i))
    ck = Checkpoint({"big": t, "small": t[:10].clone()}, {"step": i, "kind": "stage1"})
    if ws is None:
        ck.save(path)
    else:
        ws.save_version(f"v{i}", ck, kind="stage1" if i == 1 else "edit")
    print(i, flush=True)
"""


def _start_saver(target: Path, mode: str) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "REPAINT_NERF_DEVICE": "cpu"}
    return subprocess.Popen([sys.executable, "-c", _SAVER, str(target), mode], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env, cwd=ROOT)


def _kill_after_saves(proc: subprocess.Popen, saves: int, delay: float) -> int:
    """Wait until `saves` saves finished, let the next one run `delay` s, SIGKILL; returns the last finished save."""
    last = 0
    while last < saves:
        line = proc.stdout.readline()
        if not line:
            raise AssertionError(f"the saver died: {proc.stderr.read()[-2000:]}")
        last = int(line)
    time.sleep(delay)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=30)
    rest = proc.stdout.read().split()
    return int(rest[-1]) if rest else last


def _check_consistent(ck: Checkpoint) -> int:
    step = ck.header["step"]
    assert ck.header["format"] == CHECKPOINT_FORMAT
    assert torch.equal(ck.tensors["big"], torch.full((8_000_000,), float(step)))
    assert torch.equal(ck.tensors["small"], torch.full((10,), float(step)))
    return step


@pytest.mark.timeout(300)
def test_sigkill_during_checkpoint_save_keeps_last_good_one(tmp_path):
    """SIGKILL a process that saves a 32 MB checkpoint in a loop, at several moments: every time the file loads
    and is one complete save (header step matches every tensor), never older than the last save reported done."""
    path = tmp_path / "checkpoints" / "stage1.safetensors"
    mid_save = 0
    # A save takes ~40 ms on an idle machine and longer under load: sweep the kill moment over a grid of delays
    # until at least two kills landed inside a save (a temporary file is left), checking the file every time.
    delays = [0.0, 0.03, 0.08, 0.15] + [0.005 * k for k in range(1, 41)]
    for round_, delay in enumerate(delays):
        for old in path.parent.glob(".*.tmp") if path.parent.exists() else ():
            old.unlink()
        proc = _start_saver(path, "ck")
        done = _kill_after_saves(proc, 1, delay)
        mid_save += any(path.parent.glob(".*.tmp"))  # killed while a temporary file was being written
        step = _check_consistent(Checkpoint.load(path))
        assert step >= done, (round_, step, done)
        if round_ >= 3 and mid_save >= 2:
            break
    assert mid_save >= 2, "no kill landed inside a save: the test proved nothing"


@pytest.mark.timeout(90)
def test_sigkill_during_version_save_keeps_workspace_consistent(tmp_path):
    """SIGKILL while versions are being saved: the workspace opens, its index is valid JSON, every listed version
    loads, the first (the reconstruction) is unchanged, and the stale temporary files are swept on open."""
    ws_root = tmp_path / "ws"
    proc = _start_saver(ws_root, "ws")
    _kill_after_saves(proc, 2, 0.05)
    temps = list(ws_root.rglob(".*.tmp"))
    for t in temps:  # age them past the sweep threshold
        os.utime(t, (time.time() - 3600, time.time() - 3600))
    ws = Workspace.open(ws_root)
    assert not list(ws_root.rglob(".*.tmp"))
    json.loads((ws_root / "versions" / "index.json").read_text())
    assert len(ws.versions) >= 2
    for info in ws.versions:
        _check_consistent(Checkpoint.load(ws.version_path(info)))
    original = ws.original_version
    assert original.id == "v0001" and Checkpoint.load(ws.version_path(original)).header["step"] == 1


def test_sweep_keeps_fresh_temporary_files(tmp_path):
    """A temporary file younger than the threshold may belong to a live save: it stays."""
    fresh = tmp_path / ".stage1.safetensors.abc.tmp"
    fresh.write_bytes(b"x")
    old = tmp_path / ".settings.json.def.tmp"
    old.write_bytes(b"y")
    os.utime(old, (time.time() - 3600, time.time() - 3600))
    assert atomic.sweep_stale_temps(tmp_path) == [old]
    assert fresh.exists() and not old.exists()


def test_checkpoint_version_and_corruption_messages(tmp_path):
    """Another format version, a foreign safetensors file, and garbage bytes are each a WorkspaceError naming the
    file and saying what to do (no traceback-only errors)."""
    from safetensors.torch import save_file

    good = tmp_path / "good.safetensors"
    Checkpoint({"w": torch.ones(3)}, {"step": 1}).save(good)
    future = tmp_path / "future.safetensors"
    save_file({"w": torch.ones(3)}, str(future), metadata={"repaint_nerf": json.dumps({"format": 99})})
    foreign = tmp_path / "foreign.safetensors"
    save_file({"w": torch.ones(3)}, str(foreign))
    garbage = tmp_path / "garbage.safetensors"
    garbage.write_bytes(os.urandom(4096))
    for path, words in ((future, "format version 99"), (foreign, "no repaint-nerf header"),
                        (garbage, "cannot read this checkpoint")):
        with pytest.raises(WorkspaceError) as exc:
            Checkpoint.load(path)
        assert words in str(exc.value) and str(path) in str(exc.value) and "->" in str(exc.value)
    assert Checkpoint.load(good).header["step"] == 1


def _ck(value: float, kind: str = "stage1") -> Checkpoint:
    return Checkpoint({"w": torch.full((4,), value)}, {"step": int(value), "kind": kind})


def test_edits_never_overwrite_the_original_reconstruction(tmp_path):
    """Reconstruction, edits, undo, a new edit (dropping the redo line), more undo/redo: the reconstruction's file
    keeps its bytes, stays the original version, and no version file is ever reused."""
    ws = Workspace.create(tmp_path / "ws")
    rec = ws.save_version("reconstruction", _ck(1.0), kind="stage1")
    data = ws.version_path(rec).read_bytes()
    e1 = ws.save_version("blue", _ck(2.0, "edit"))
    ws.undo()
    e2 = ws.save_version("red", _ck(3.0, "edit"))
    ws.undo()
    ws.undo()
    ws.redo()
    e3 = ws.save_version("green", _ck(4.0, "edit"))
    files = [v.file for v in (rec, e1, e2, e3)]
    assert len(set(files)) == 4
    assert ws.version_path(rec).read_bytes() == data
    assert ws.original_version.id == rec.id
    assert Checkpoint.load(ws.version_path(e1)).header["step"] == 2  # an undone edit's file survives too
    assert [v.id for v in ws.versions] == [rec.id, e2.id, e3.id]


def test_finished_edit_autosaves_a_version(tmp_path):
    """A repaint edit that finishes saves itself as a new 'edit' version (no explicit save): the file restores a
    field that renders like the edited one in memory, and the reconstruction version is untouched."""
    from repaint_nerf.core.field.field import FieldConfig, NGPField
    from repaint_nerf.core.render.occupancy import OccupancyGrid
    from repaint_nerf.core.render.renderer import RenderOptions, render_rays
    from repaint_nerf.core.repaint.trainer import RepaintTrainer
    from repaint_nerf.core.scene.loaders.detect import load_scene
    from repaint_nerf.core.synth.generate import make_scene
    from repaint_nerf.core.train.stage1 import restore_field

    scene = load_scene(make_scene("demo", tmp_path / "demo", size=16, views=4, seed=0, test_views=1), 1.0)
    cfg = FieldConfig(levels=4, log2_table=12, base_res=8, finest_res=64, hidden=16, geo_feat_dim=7, sh_degree=2,
                      encoding_impl="indexed", compile=False)
    torch.manual_seed(0)
    field, grid = NGPField(cfg), OccupancyGrid(resolution=16, bound=1.0)
    ws = Workspace.create(tmp_path / "ws")
    rec = ws.save_version("reconstruction", _ck(1.0), kind="stage1")
    rec_bytes = ws.version_path(rec).read_bytes()
    masks = [np.pad(np.ones((6, 6), bool), 5) for _ in scene.train.images]
    rp = RepaintTrainer(scene, field, grid, workspace=ws, masks=masks, guidance="recolor", prompt="a blue box",
                        steps=3, resolution=16, max_samples=32, snapshot_every=0, region_resolution=16)
    rp.run()
    cur = ws.current_version
    assert rp.done and cur.kind == "edit" and cur.id != rec.id and rp.version.id == cur.id
    assert ws.version_path(rec).read_bytes() == rec_bytes
    f2, g2, header = restore_field(Checkpoint.load(ws.version_path(cur)), "cpu")
    assert header.kind == "edit" and header.edit.steps == 3
    o = torch.tensor([[0.0, 0.0, -3.0], [0.2, 0.1, -3.0]])
    d = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    with torch.no_grad():
        a = render_rays(field.eval(), grid, o, d, RenderOptions(max_samples=64))
        b = render_rays(f2, g2, o, d, RenderOptions(max_samples=64))
    torch.testing.assert_close(a["rgb"], b["rgb"])
