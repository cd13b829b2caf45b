"""Real captures in the benchmarks (issue 32 part 4), offline: the every-Nth held-out views, the capture registry and
its preparation from a git snapshot or a folder, and the evaluation times of `bench recon`."""
from __future__ import annotations

import json
import math
import subprocess
from pathlib import Path

import numpy as np
import pytest

from repaint_nerf.core.bench.capture_prepare import SOURCE_FILE, prepare
from repaint_nerf.core.bench.captures import CAPTURES, Capture, find_capture
from repaint_nerf.core.bench.recon import at_times, eval_times
from repaint_nerf.core.errors import UserError
from repaint_nerf.core.scene.cameras import look_at
from repaint_nerf.core.scene.loaders.detect import load_scene
from scene_writers import pattern, ring_poses, write_blender, write_image, write_llff


def _forward_poses(n: int) -> np.ndarray:
    return np.stack([look_at([0.3 * math.cos(i), 0.2 * math.sin(i), 4.0], [0, 0, 0], up=(0, 1, 0)) for i in range(n)])


def _write_ngp(root: Path, n: int, missing=()) -> None:
    """A tiny instant-ngp capture: frames listed out of file order, some without an image."""
    poses = ring_poses(n)
    frames = [{"file_path": f"images/{i:03d}.png", "transform_matrix": poses[i].tolist()} for i in range(n)]
    for i in range(n):
        if i not in missing:
            write_image(root / "images" / f"{i:03d}.png", pattern(12, 16, i))
    meta = {"fl_x": 14.0, "fl_y": 14.0, "cx": 8.0, "cy": 6.0, "w": 16, "h": 12, "aabb_scale": 4,
            "frames": frames[::-1]}
    (root / "transforms.json").write_text(json.dumps(meta))


def _names(scene, split: str) -> list[str]:
    return sorted(Path(n).name for n in scene.splits[split].names)


# ------------------------------------------------------------------ held-out views


def test_llff_holds_out_every_nth_view_and_says_so(tmp_path):
    write_llff(tmp_path, _forward_poses(17), h=12, w=16, focal=14.0, bounds=np.tile([2.0, 6.0], (17, 1)))
    s8 = load_scene(tmp_path)
    assert _names(s8, "test") == ["IMG_000.png", "IMG_008.png", "IMG_016.png"] and len(s8.train) == 14
    s4 = load_scene(tmp_path, holdout_every=4)
    assert _names(s4, "test") == [f"IMG_{i:03d}.png" for i in (0, 4, 8, 12, 16)]
    assert not set(_names(s4, "test")) & set(_names(s4, "train"))
    assert s4.extra["holdout"]["every"] == 4 and "not trained on" in s4.extra["holdout"]["rule"]


def test_transforms_json_holds_out_every_nth_frame_with_an_image_in_file_order(tmp_path):
    _write_ngp(tmp_path, 20, missing=(3,))
    with pytest.warns(Warning):
        scene = load_scene(tmp_path, holdout_every=8)
    # frames with an image, sorted by path: 000 001 002 004 ... -> positions 0, 8, 16 are 000, 009, 017
    assert _names(scene, "test") == ["000.png", "009.png", "017.png"] and len(scene.train) == 16
    assert scene.extra["holdout"]["order"].startswith("frames with an image")


def test_a_synthetic_scene_keeps_its_own_test_split(tmp_path):
    write_blender(tmp_path, counts={"train": 9, "test": 3})
    scene = load_scene(tmp_path, holdout_every=2)
    assert len(scene.train) == 9 and len(scene.splits["test"]) == 3
    assert scene.extra["holdout"] == {"rule": "the dataset's own test split"}


@pytest.mark.parametrize("every", [0, 1, -8, 2.5])
def test_bad_holdout_every_says_what_to_give(tmp_path, every):
    write_llff(tmp_path, _forward_poses(3), h=12, w=16, focal=14.0, bounds=np.tile([2.0, 6.0], (3, 1)))
    with pytest.raises(UserError, match="--holdout-every must be a whole number >= 2"):
        load_scene(tmp_path, holdout_every=every)


def test_poses_bounds_of_a_360_capture_is_not_read_as_forward_facing(tmp_path):
    write_llff(tmp_path, ring_poses(16), h=12, w=16, focal=14.0, bounds=np.tile([2.0, 6.0], (16, 1)))
    scene = load_scene(tmp_path)
    assert scene.format == "llff" and scene.kind != "forward" and scene.extra["kind_reason"]


# ------------------------------------------------------------------ registry and preparation


def _git(repo: Path, *args: str) -> str:
    return subprocess.run(["git", "-C", str(repo), *args], check=True, capture_output=True, text=True).stdout.strip()


@pytest.fixture
def snapshot(tmp_path) -> tuple[Path, str]:
    """A git repository holding a capture under data/cap, whose snapshot lacks one image blob and ships one LFS
    pointer: (git dir, commit)."""
    work = tmp_path / "repo"
    _write_ngp(work / "data" / "cap", 10)
    (work / "data" / "cap" / "big.bin").write_text("version https://git-lfs.github.com/spec/v1\noid sha256:00\n")
    (work / "other.txt").write_text("not part of the capture")
    _git(work, "init", "-q")
    _git(work, "add", ".")
    _git(work, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "capture")
    oid = _git(work, "rev-parse", "HEAD:data/cap/images/005.png")
    (work / ".git" / "objects" / oid[:2] / oid[2:]).unlink()  # the snapshot lists it but lacks it
    return work / ".git", _git(work, "rev-parse", "HEAD")


def _cap(commit: str) -> Capture:
    return Capture("tiny", "someone/tiny", commit, "data/cap", "object in its room", "transforms.json", "10 x 16x12",
                   "test")


def test_prepare_copies_what_the_snapshot_has_as_shipped(snapshot, tmp_path):
    git_dir, commit = snapshot
    res = prepare(_cap(commit), git_dir, tmp_path / "caps", shrink=(2,))
    folder = tmp_path / "caps" / "tiny"
    assert res.folder == folder and sorted(res.missing) == ["big.bin", "images/005.png"]
    assert not (folder / "other.txt").exists() and not (folder / "big.bin").exists()
    src = json.loads((git_dir.parent / "data" / "cap" / "transforms.json").read_text())
    assert json.loads((folder / "transforms.json").read_text()) == src  # byte for byte, no edits
    assert len(list((folder / "images_2").iterdir())) == 9 and res.shrunk == {2: 9}
    note = json.loads((folder / SOURCE_FILE).read_text())
    assert note["source"]["commit"] == commit and note["capture"]["repo"] == "someone/tiny"
    with pytest.warns(Warning, match="skipped 1 of 10 frames"):
        scene = load_scene(folder)  # opens without edits: the missing image's frame is skipped
    assert len(scene.train) + len(scene.splits["test"]) == 9


def test_prepare_refuses_an_existing_folder_a_wrong_commit_and_bad_factors(snapshot, tmp_path):
    git_dir, commit = snapshot
    prepare(_cap(commit), git_dir, tmp_path)
    with pytest.raises(UserError, match="already exists"):
        prepare(_cap(commit), git_dir, tmp_path)
    prepare(_cap(commit), git_dir, tmp_path, force=True)
    with pytest.raises(UserError, match="does not hold commit"):
        prepare(_cap("0" * 40), git_dir, tmp_path / "x")
    with pytest.raises(UserError, match="--shrink"):
        prepare(_cap(commit), git_dir, tmp_path / "y", shrink=(1,))
    with pytest.raises(UserError, match="no such file"):
        prepare(_cap(commit), tmp_path / "nowhere", tmp_path / "z")


def test_prepare_from_a_plain_folder(tmp_path):
    _write_ngp(tmp_path / "src" / "data" / "cap", 4)
    res = prepare(_cap("unused"), tmp_path / "src", tmp_path / "caps")
    assert res.copied == 5 and (res.folder / "transforms.json").is_file()
    assert json.loads((res.folder / SOURCE_FILE).read_text())["source"]["folder"].endswith("data/cap")


def test_registry_names_three_kinds_and_unknown_names_are_explained():
    assert len({c.name for c in CAPTURES}) == len(CAPTURES) >= 3
    assert all(len(c.commit) == 40 and "/" in c.repo for c in CAPTURES)
    assert find_capture("fox").repo == "NVlabs/instant-ngp"
    with pytest.raises(UserError, match="no capture called"):
        find_capture("nope")


# ------------------------------------------------------------------ bench recon's evaluation times


def test_eval_times_hold_the_first_minute_and_the_report_times():
    assert eval_times(60, 2, (60.0, 120.0, 300.0)) == [10, 20, 30, 40, 50, 60]
    t = eval_times(300, 3, (60.0, 120.0, 300.0))
    assert t == [10, 20, 30, 40, 50, 60, 100, 120, 200, 300]
    assert eval_times(30, 1, (60.0,), minute_curve=False) == [30]
    curve = [{"target": x, "psnr": x / 10} for x in t]
    at = at_times(curve, (60.0, 120.0, 600.0))
    assert at["60"]["psnr"] == 6.0 and at["120"]["psnr"] == 12.0 and at["600"] is None


def test_a_capture_scores_every_pixel_only_at_the_report_times(tmp_path):
    """bench recon on a capture: the untrained field's point and the curve between report times take the bounded
    evaluation (marked), the report times every pixel with SSIM; a synthetic split keeps full points throughout."""
    from repaint_nerf.core.bench.recon import measure

    write_llff(tmp_path, _forward_poses(17), h=12, w=16, focal=14.0, bounds=np.tile([2.0, 6.0], (17, 1)))
    res = measure(tmp_path, 2.0, evals=2, report_at=(1.0,), minute_curve=False, profile_steps=1)
    by_target = {p.get("target"): p for p in res["curve"]}
    assert res["curve"][0]["bounded"] and by_target[1.0].get("bounded") is None and "ssim" in by_target[1.0]
    assert by_target[2.0]["bounded"] and "only at the report times" in res["evaluation"]["pixels"]
    full = measure(tmp_path, 2.0, evals=2, report_at=(1.0,), minute_curve=False, profile_steps=1,
                   bounded_curve=False)
    assert all("bounded" not in p for p in full["curve"][1:])
    forced = measure(tmp_path, 1.0, evals=1, report_at=(0.5,), minute_curve=False, profile_steps=1, kind="unbounded")
    assert (res["scene"]["kind"], forced["scene"]["kind"]) == ("forward", "unbounded")  # as train --kind


def test_as_train_measures_what_the_train_command_trains_and_leaves_no_workspace(tmp_path, monkeypatch):
    """bench recon trains colour alone by default, as nerfacto does; --as-train adds the train command's teacher
    features and depth priors, computed in a temporary workspace that is gone afterwards."""
    import tempfile

    from repaint_nerf.core.bench.recon import measure

    scratch = tmp_path / "tmp"
    scratch.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))
    write_llff(tmp_path / "s", _forward_poses(9), h=12, w=16, focal=14.0, bounds=np.tile([2.0, 6.0], (9, 1)))
    kw = dict(evals=1, report_at=(0.5,), minute_curve=False, profile_steps=1)
    colour = measure(tmp_path / "s", 0.5, **kw)
    assert colour["trains"].startswith("colour alone")
    res = measure(tmp_path / "s", 0.5, as_train=True, **kw)
    trains = res["trains"]
    assert trains["as"].startswith("the train command") and trains["feature_dim"] > 0, trains
    assert trains["features"] != "the default teacher" and trains["depth_priors_s"] >= 0
    assert trains["depth_priors"] in (None, "triangulated from the known poses")  # an LLFF scene has no SfM points
    assert trains["depth_priors"] is not None or any("depth" in n for n in trains["notes"])
    # torch.compile's cache (torchinductor_USER) lands in the temp folder when this test runs first: not ours
    left = [p for p in scratch.iterdir() if not p.name.startswith("torchinductor")]
    assert not left, left


# ------------------------------------------------------------------ the nerfacto harness (no nerfstudio needed)


def test_nerfacto_dataset_holds_the_same_views_and_split_as_bench_recon(tmp_path):
    from repaint_nerf.core.bench.nerfacto import export_scene, train_command

    write_llff(tmp_path / "cap", _forward_poses(10), h=12, w=16, focal=14.0, bounds=np.tile([2.0, 6.0], (10, 1)))
    scene = load_scene(tmp_path / "cap")
    meta = export_scene(scene, tmp_path / "ns")
    assert len(meta["test_filenames"]) == 2 and meta["val_filenames"] == meta["test_filenames"]
    assert len(meta["train_filenames"]) == 8 and all((tmp_path / "ns" / f["file_path"]).is_file()
                                                      for f in meta["frames"])
    assert meta["frames"][0]["fl_x"] == 14.0 and meta["frames"][0]["w"] == 16
    first = export_scene(scene, tmp_path / "ns1", eval_views=1)  # bench recon --eval-views 1 scores the first
    assert first["test_filenames"] == meta["test_filenames"][:1] and first["train_filenames"] == meta["train_filenames"]
    cmd = train_command(Path("/venv/bin"), tmp_path / "ns", tmp_path / "out", 25)
    assert "nerfacto" in cmd and "NoLPIPS" in cmd[2] and "cpu" in cmd and cmd[cmd.index("--data") + 1] == str(tmp_path / "ns")


def test_nerfacto_without_nerfstudio_says_how_to_install_it(tmp_path):
    from repaint_nerf.core.bench.nerfacto import measure

    with pytest.raises(UserError, match="no ns-train"):
        measure(tmp_path, 10, tmp_path / "no-venv", tmp_path / "work")


def test_captures_table_puts_both_methods_side_by_side_and_docs_render_it(tmp_path, capsys):
    """bench captures --table gathers bench recon's and bench nerfacto's JSON per capture; repaint-nerf docs shows
    them as one table (a missing nerfacto run leaves its row out, not a crash)."""
    from repaint_nerf.app.benchdocs.details import SECTIONS
    from repaint_nerf.app.cli import main

    ours = {"scene": {"name": "fox", "kind": "unbounded", "size": [512, 288], "train_views": 43, "test_views": 7},
            "at": {"60": {"psnr": 20.4, "ssim": 0.59, "step": 255, "seconds": 60.1},
                   "300": {"psnr": 25.9, "ssim": 0.76, "step": 1154, "seconds": 300.0}},
            "samples_per_ray": {"with_grid": 43.1}, "steps_per_s": 3.85}
    theirs = {"at": {"60": None, "300": {"psnr": 12.0, "ssim": 0.4, "step": 100, "seconds": 290.0},
                     "1800": {"psnr": 18.5, "ssim": 0.5, "step": 700, "seconds": 1790.0}}, "steps_per_s": 0.39}
    (tmp_path / "o.json").write_text(json.dumps(ours))
    (tmp_path / "n.json").write_text(json.dumps(theirs))
    out = tmp_path / "captures.json"
    assert main(["bench", "captures", "--table", f"fox={tmp_path / 'o.json'},{tmp_path / 'n.json'}",
                 "--table", f"fern={tmp_path / 'o.json'}", "--json", str(out)]) == 0
    table = json.loads(out.read_text())
    fox = table["captures"]["fox"]
    assert fox["ours"]["samples_per_ray"] == 43.1 and fox["nerfacto"]["longest"]["psnr"] == 18.5
    assert table["captures"]["fern"]["nerfacto"] is None
    text = SECTIONS["captures"][1](table)
    assert "| fox | ours, colour alone | 20.40 |" in text and "18.50 at 1790 s" in text and text.count("| fern |") == 1
    assert main(["bench", "captures", "--table", "fox"]) != 0
    assert "NAME=OURS.json" in capsys.readouterr().err
    # --update replaces the rows given and keeps the others (a capture measured on another day)
    assert main(["bench", "captures", "--table", f"fern={tmp_path / 'o.json'},{tmp_path / 'n.json'}", "--update",
                 "--json", str(out)]) == 0
    updated = json.loads(out.read_text())
    assert updated["captures"]["fox"] == fox and updated["captures"]["fern"]["nerfacto"]["longest"]["psnr"] == 18.5
    # our side re-measured alone (a speed-up) keeps nerfacto's row; without --update a row has none
    faster = {**ours, "at": {"60": {"psnr": 23.1, "ssim": 0.7, "step": 700, "seconds": 60.0}}, "steps_per_s": 11.0,
              "trains": {"as": "the train command: colour, teacher features and depth priors (paper Eq. s1)"}}
    (tmp_path / "o2.json").write_text(json.dumps(faster))
    assert main(["bench", "captures", "--table", f"fox={tmp_path / 'o2.json'}", "--update", "--json", str(out)]) == 0
    again = json.loads(out.read_text())["captures"]
    # an --as-train run (what `train` trains) gets its own row beside the colour-alone one, which it keeps
    assert again["fox"]["ours_as_train"]["steps_per_s"] == 11.0 and again["fox"]["ours"] == fox["ours"]
    assert again["fox"]["nerfacto"] == fox["nerfacto"]
    shown = SECTIONS["captures"][1](json.loads(out.read_text()))
    assert "| fox | ours, as train | 23.10 |" in shown and "| fox | ours, colour alone | 20.40 |" in shown
    assert again["fern"] == updated["captures"]["fern"]
    assert main(["bench", "captures", "--table", f"fern={tmp_path / 'o.json'}", "--update", "--json",
                 str(tmp_path / "none.json")]) != 0
    assert "existing table" in capsys.readouterr().err
