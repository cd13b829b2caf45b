"""`bench edit` (issue 16 item 5): the drift case's border split and a tiny end-to-end run's schema."""
from __future__ import annotations

import json

import numpy as np


def test_border_regions_split_the_unmasked_pixels_into_a_band_and_the_rest():
    from repaint_nerf.core.bench.edit import border_regions

    m = np.zeros((9, 11), bool)
    m[3:5, 4:6] = True
    reg = border_regions([m], 2)
    yy, xx = np.mgrid[:9, :11]
    # Chebyshev distance to the nearest mask pixel, written out
    dist = np.min([np.maximum(abs(yy - y), abs(xx - x)) for y, x in zip(*np.nonzero(m))], axis=0)
    band = (dist >= 1) & (dist <= 2)
    # "band" leaves out everything but the band; "far" leaves out the mask and the band
    np.testing.assert_array_equal(~reg["band"][0], band)
    np.testing.assert_array_equal(~reg["far"][0], dist > 2)


def test_bench_edit_drift_reports_its_curve_and_border_split(scene_factory, tmp_path, capsys):
    from repaint_nerf.app.cli import main
    from repaint_nerf.core.bench.edit import DRIFT_GOAL
    from repaint_nerf.core.repaint.config import RepaintConfig

    scene = scene_factory("demo", size=16, views=6, test_views=2)
    out = tmp_path / "edit.json"
    assert main(["bench", "edit", "--scene", str(scene), "--stage1-steps", "10", "--rays", "256", "--steps", "4",
                 "--evals", "2", "--no-ablation", "--no-offline", "--json", str(out)]) == 0
    res = json.loads(out.read_text())
    assert next(iter(res)) == "drift"
    d = res["drift"]
    cfg = RepaintConfig()
    assert (d["lambda_unmask"], d["unmask_reduction"]) == (cfg.lambda_unmask, cfg.unmask_reduction)
    assert (d["unmask_ramp"], d["unmask_ramp_start"]) == (cfg.unmask_ramp, cfg.unmask_ramp_start)
    assert [r["step"] for r in d["curve"]] == [0, 2, 4]
    assert d["psnr_masked"] == d["curve"][-1]["psnr_masked"]
    assert d["unmasked_drop_db"] == d["psnr_unmasked_before"] - d["psnr_unmasked"]
    # the verdict is issue 16's goal for the defaults, both halves
    assert d["ok"] == (d["unmasked_drop_db"] <= DRIFT_GOAL["unmasked_drop_db"]
                       and d["psnr_masked"] >= DRIFT_GOAL["psnr_masked"])
    assert d["border_px"] == 1  # 16 px / 32, at least one
    for part in (d["border"], d["beyond_border"]):
        assert part["drop_db"] == part["psnr_before"] - part["psnr"]
    text = capsys.readouterr().out
    assert "drop within 1 px of the object" in text and "masked dB along the edit" in text
    assert ("-> ok" if d["ok"] else "-> NOT ok") in text
