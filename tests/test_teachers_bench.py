"""`bench teacher` on a photograph: the mask a patch gives, its area, and the picture; measurement in
core/bench/teacher.py, driver in app/bench/teacher.py."""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest


def two_region_photo(h: int = 60, w: int = 80) -> np.ndarray:
    """A left region of noisy dark blue cloth and a right region of noisy light wood, RGB uint8."""
    rng = np.random.default_rng(0)
    img = np.empty((h, w, 3), np.float32)
    img[:, : w // 2] = (30, 40, 110)
    img[:, w // 2:] = (200, 160, 110)
    img += rng.normal(0, 6, img.shape)
    return np.clip(img, 0, 255).astype(np.uint8)


def test_photo_mask_from_a_patch_covers_its_region():
    from repaint_nerf.core.bench.teacher import evaluate_photo, patch_box
    from repaint_nerf.core.teachers.feature_default import DEFAULT_THRESHOLD, DefaultFeatureTeacher

    img = two_region_photo()
    box = patch_box((0.1, 0.3, 0.3, 0.6), 60, 80)
    assert box == (18, 36, 8, 24)
    res, maps = evaluate_photo(img, box, DefaultFeatureTeacher(), DEFAULT_THRESHOLD)
    left = np.zeros((60, 80), bool)
    left[:, :40] = True
    assert maps["mask"].shape == (60, 80) and maps["sim"].dtype == np.float32
    assert res["area_fraction"] == pytest.approx(maps["mask"].mean())
    inter, union = np.sum(maps["mask"] & left), np.sum(maps["mask"] | left)
    assert inter / union > 0.9  # the patch's region, not the other one
    areas = list(res["area_by_threshold"].values())
    assert all(a >= b for a, b in zip(areas, areas[1:]))  # a higher threshold never grows the mask
    res2, maps2 = evaluate_photo(img, box, DefaultFeatureTeacher(), DEFAULT_THRESHOLD,
                                 refine=lambda masks: [m & left for m in masks])
    assert res2["area_fraction_refined"] == pytest.approx(np.mean(maps2["refined"]))


def test_bench_teacher_cli_on_a_photo(tmp_path, capsys):
    from repaint_nerf.app.cli import main

    photo = tmp_path / "photo.png"
    cv2.imwrite(str(photo), two_region_photo()[..., ::-1])
    out = tmp_path / "b.json"
    assert main(["bench", "teacher", "--no-presets", "--photo", str(photo), "--photo-patch", "0.1,0.3,0.3,0.6",
                 "--json", str(out)]) == 0
    assert "covers" in capsys.readouterr().out
    doc = json.loads(out.read_text())
    area = doc["photo"]["teachers"]["default"]["area_fraction"]
    assert 0.4 < area < 0.6 and doc["summary"]["photo_area_fraction"] == {"default": area}
    pic = cv2.imread(str(tmp_path / "b_photo.png"))
    assert pic.shape == (26 + 300, 3 * 400, 3)  # label strip over photo | similarity | mask, 300 px tall
    assert main(["bench", "teacher", "--no-presets", "--photo", str(photo), "--photo-patch", "0.5,0.1,0.2,0.9",
                 "--json", str(out)]) == 2
    assert "--photo-patch" in capsys.readouterr().err
    assert main(["bench", "teacher", "--no-presets", "--photo", str(tmp_path / "none.jpg"), "--json", str(out)]) == 2
