"""`bench scale` (issue 18 item 4): a tiny run writes the asked schema, with the types it promises, and a plot."""
from __future__ import annotations

import json

import pytest

KEYS = {"size": int, "seconds_to_10": (float, type(None)), "seconds_to_12.5": (float, type(None)),
        "steps_per_s_early": (float, type(None)), "steps_per_s": (float, type(None)), "samples_per_ray": float,
        "render_ms": float, "eval_seconds": float, "train_seconds": float, "peak_rss_mb": float}


def test_bench_scale_writes_the_schema(scene_factory, tmp_path, capsys):
    from repaint_nerf.app.cli import main

    scene = scene_factory("demo", size=48, views=6, test_views=3)
    out = tmp_path / "scale.json"
    assert main(["bench", "scale", "--scene", str(scene), "--sizes", "32,48", "--seconds", "3", "--evals", "1",
                 "--early-seconds", "1", "--rays", "512", "--targets", "12.5,10", "--json", str(out)]) == 0
    res = json.loads(out.read_text())
    assert res["targets"] == [10.0, 12.5]  # the PSNRs timed, sorted; a demo at 3 s passes 10 dB
    assert [e["size"] for e in res["sizes"]] == [32, 48]
    for e in res["sizes"]:
        for key, kind in KEYS.items():
            assert isinstance(e[key], kind), (key, e[key])
        assert max(e["image_size"]) == e["size"]  # the scene loaded at that long side
        assert e["train_seconds"] >= 3.0 and e["peak_rss_mb"] > 100
        assert 1 <= e["steps_early"] <= e["steps"] and e["steps_per_s_early"] > 0  # the first second's steps
        assert (e["steps_per_s"] is None) == (e["steps_early"] == e["steps"])
        # the evenly spaced evaluation (the end) and one every second before it (--dense-until's default, 10 s)
        assert [round(p["seconds"]) for p in e["curve"][:-1]] == [0, 1, 2] and e["curve"][-1]["seconds"] >= 3.0
        assert e["curve"][0]["step"] == 0 and e["curve"][-1]["step"] == e["steps"]
        assert all(key in e for key in ("steps_to_10", "steps_to_12.5", "msamples_to_10", "msamples_to_12.5"))
        assert "seconds_to_30" not in e
        assert e["seconds_to_10"] is not None and e["final_psnr"] > 10
        assert e["curve"][-1]["msamples"] > e["curve"][0]["msamples"] == 0.0
        steps = [r["step"] for r in e["trace"]]  # the trace follows training in order
        assert steps and steps == sorted(steps) and steps[-1] <= e["steps"]
        assert all(r["steps_per_s"] > 0 and r["samples_per_ray"] > 0 and 0 <= r["occupied"] <= 1 for r in e["trace"])
    small, large = res["sizes"]
    # the larger size is also scored on the smaller size's images, at every evaluation
    assert small["content_size"] is None and small["detail_ceiling_psnr"] is None
    assert "seconds_to_10_content" not in small and "psnr_content" not in small["curve"][0]
    assert large["content_size"] == 32 and all(isinstance(p["psnr_content"], float) for p in large["curve"])
    assert isinstance(large["seconds_to_10_content"], (float, type(None)))
    assert 5.0 < large["detail_ceiling_psnr"] < 60.0
    assert res["isolated_processes"] and "bounded evaluation" in res["psnr_measured"] and res["dense_until"] == 10
    assert out.with_suffix(".png").stat().st_size > 1000
    printed = capsys.readouterr().out
    assert "wrote" in printed and "s->12.5" in printed and "s->30" not in printed and "s->12.5@32" in printed


def test_detail_ceiling_is_what_the_smaller_images_lack(scene_factory):
    """The same images score no loss; images loaded smaller lose more the smaller they are, as a plain bilinear
    round trip of the larger images says."""
    import cv2
    import numpy as np
    import torch

    from repaint_nerf.core.bench.scale import detail_ceiling
    from repaint_nerf.core.scene.loaders.detect import load_scene

    path = scene_factory("bread", size=64, views=4, test_views=2)
    big, half, quarter = (load_scene(path, max_size=s) for s in (64, 32, 16))
    white = torch.ones(3)
    assert detail_ceiling(big, load_scene(path, max_size=64), white) == pytest.approx(120.0)
    assert detail_ceiling(big, half, white) > detail_ceiling(big, quarter, white) + 1.0

    def on_white(im):
        x = np.asarray(im, np.float64) / 255.0
        return x[..., :3] * x[..., 3:] + 1.0 - x[..., 3:]

    ref = []
    for im, small in zip(big.splits["test"].images, half.splits["test"].images):
        low = cv2.resize(on_white(small), (64, 64), interpolation=cv2.INTER_LINEAR)
        ref.append(-10 * np.log10(np.mean((low - on_white(im)) ** 2)))
    assert detail_ceiling(big, half, white) == pytest.approx(float(np.mean(ref)), abs=1e-3)


def test_evaluate_scores_another_load_of_the_same_capture(scene_factory):
    """evaluate(scene=...) renders the other load's cameras through this scene's normalisation: the same load scores
    the same, and a smaller one scores a blurred target."""
    from repaint_nerf.core.scene.loaders.detect import load_scene
    from repaint_nerf.core.train.stage1 import Stage1Trainer, TrainConfig

    path = scene_factory("demo", size=48, views=6, test_views=3)
    scene = load_scene(path, max_size=48)
    trainer = Stage1Trainer(scene, None, TrainConfig(seed=0, rays_per_batch=512), device="cpu")
    trainer.train(steps=30)
    own = trainer.evaluate()
    assert trainer.evaluate(scene=load_scene(path, max_size=48))["psnr"] == pytest.approx(own["psnr"], abs=1e-6)
    other = trainer.evaluate(scene=load_scene(path, max_size=24))
    assert other["pixels"] < own["pixels"] and other["psnr"] != pytest.approx(own["psnr"], abs=1e-3)


def test_bench_scale_bad_sizes_are_a_user_error(tmp_path):
    from repaint_nerf.app.cli import main

    for bad in ("", "128,x", "4"):
        assert main(["bench", "scale", "--sizes", bad, "--json", str(tmp_path / "o.json")]) != 0


def test_bench_scale_bad_targets_are_a_user_error(tmp_path, capsys):
    from repaint_nerf.app.cli import main

    for bad in ("", "25,x", "0", "120"):
        assert main(["bench", "scale", "--sizes", "32", "--targets", bad, "--json", str(tmp_path / "o.json")]) != 0
        assert "--targets" in capsys.readouterr().err
    assert not (tmp_path / "o.json").exists()  # refused before any training


def test_bench_scale_a_negative_dense_until_is_a_user_error(tmp_path, capsys):
    from repaint_nerf.app.cli import main

    assert main(["bench", "scale", "--sizes", "32", "--dense-until", "-1", "--json", str(tmp_path / "o.json")]) != 0
    assert "--dense-until" in capsys.readouterr().err and not (tmp_path / "o.json").exists()


def test_time_to_interpolates_between_evaluations():
    from repaint_nerf.core.bench.recon import time_to

    curve = [{"seconds": 0.0, "psnr": 10.0}, {"seconds": 10.0, "psnr": 20.0}, {"seconds": 20.0, "psnr": 30.0}]
    assert time_to(curve, 25.0) == pytest.approx(15.0)
    assert time_to(curve, 31.0) is None
