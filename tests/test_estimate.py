"""Repaint time estimate: scaling with pixels, steps and options against the stored figures, time left from
measured steps, the trainer's progress fields, and the `repaint` command printing both."""
from __future__ import annotations

import pytest
import torch

from repaint_nerf.core.repaint import estimate as est
from repaint_nerf.core.repaint.estimate import Progress, estimate_before_start, estimate_repaint, format_duration, sd_step_seconds
from repaint_scene import make_field, make_grid, make_scene

CPU = torch.device("cpu")


def test_sd_step_scales_with_sds_pixels_and_options():
    s512, fixed = est.SD_STEP_SECONDS_512["cpu"][("fp32", False, False)]
    full, how = sd_step_seconds(CPU, "fp32", False, 512)
    assert full == s512 and "bench sdcost" in how
    # a fixed part plus a part per pixel: 256 px (1/4 of the pixels) costs f + (1 - f) / 4 of 512 px
    assert sd_step_seconds(CPU, "fp32", False, 256)[0] == pytest.approx(s512 * (fixed + (1 - fixed) / 4))
    assert sd_step_seconds(CPU, "fp32", False, 1024)[0] == pytest.approx(s512 * (fixed + 4 * (1 - fixed)))
    assert sd_step_seconds(CPU, "fp32", False, None)[0] == full  # the model's own 512 px
    bf16_tiny = sd_step_seconds(CPU, "bf16", True, 512, token_merging=0.0)[0]
    assert bf16_tiny == est.SD_STEP_SECONDS_512["cpu"][("bf16", True, False)][0] < full
    assert sd_step_seconds("meta", "fp32")[0] is None  # no figure for that device kind


def test_sd_step_with_token_merging():
    merged, how = sd_step_seconds(CPU, "bf16", True, 512, token_merging=0.5)
    assert merged == est.SD_STEP_SECONDS_512["cpu"][("bf16", True, True)][0] and "token merging" in how
    assert merged < sd_step_seconds(CPU, "bf16", True, 512, token_merging=0.0)[0]
    assert sd_step_seconds(CPU, "bf16", True, 512)[0] == merged  # RepaintConfig's default merges
    # not measured with fp32 and the VAE: the figure without it, and the note says so
    plain = sd_step_seconds(CPU, "fp32", False, 256)
    merged_fp32 = sd_step_seconds(CPU, "fp32", False, 256, token_merging=0.5)
    assert merged_fp32[0] == plain[0] and "not measured" in merged_fp32[1]
    e = estimate_repaint("sd", 10, (64, 64), CPU, unet_precision="bf16", tiny_autoencoder=True, token_merging=0.5)
    assert e.guidance_seconds == merged


def test_estimate_scales_with_render_pixels_and_steps():
    a = estimate_repaint("sd", 100, (64, 64), CPU, unet_precision="fp32")
    b = estimate_repaint("sd", 100, (128, 128), CPU, unet_precision="fp32")
    assert b.field_seconds == pytest.approx(4 * a.field_seconds)
    assert a.field_seconds == pytest.approx(est.FIELD_SECONDS_PER_MPIX["cpu"] * 64 * 64 / 1e6)
    assert b.guidance_seconds == a.guidance_seconds  # SD sees every render at its own resolution
    assert a.total_seconds == pytest.approx(100 * (a.field_seconds + a.guidance_seconds))
    c = estimate_repaint("sd", 300, (64, 64), CPU, unet_precision="fp32")
    assert c.total_seconds == pytest.approx(3 * a.total_seconds)
    timed = estimate_repaint("recolor", 10, (64, 64), CPU, field_step_seconds=0.5)
    assert timed.guidance_seconds == 0.0 and timed.total_seconds == pytest.approx(5.0)
    assert "timed on this device" in timed.describe() and "5 s" in timed.describe()


def test_estimate_before_start_uses_the_trainers_resolution():
    e = estimate_before_start("recolor", 10, 1920, 1080, CPU)
    assert e.field_seconds == pytest.approx(est.FIELD_SECONDS_PER_MPIX["cpu"] * 128 * 72 / 1e6)
    e = estimate_before_start("recolor", 10, 1920, 1080, CPU, resolution=256)
    assert e.field_seconds == pytest.approx(est.FIELD_SECONDS_PER_MPIX["cpu"] * 256 * 144 / 1e6)
    unknown = estimate_before_start("sd", 10, 64, 64, "meta")
    assert unknown.total_seconds is None and "unknown" in unknown.describe()


def test_progress_time_left_from_measured_steps():
    p = Progress(10, prior_step_seconds=2.0)
    assert p.seconds_left(0) == 20.0
    p.update(9.0)  # warm-up step: used only while it is the only one
    assert p.seconds_left(1) == pytest.approx(81.0)
    p.update(1.0)
    p.update(3.0)
    assert p.seconds_left(3) == pytest.approx(7 * 2.0)
    assert p.seconds_left(12) == 0.0


def test_format_duration():
    assert format_duration(45) == "45 s" and format_duration(600) == "10 min"
    assert format_duration(3 * 3600 + 20 * 60) == "3 h 20 min" and format_duration(3 * 86400 + 7200) == "3 d 2 h"
    assert format_duration(None) == "?"


def test_trainer_reports_steps_and_time_left_and_times_without_changing_the_field():
    from repaint_nerf.core.repaint.trainer import RepaintTrainer

    scene, masks = make_scene()
    field = make_field()
    tr = RepaintTrainer(scene, field, make_grid(field), masks=masks, guidance="recolor", prompt="make it blue",
                        steps=4, max_samples=128)
    before = {k: v.clone() for k, v in field.state_dict().items()}
    e = tr.estimate()
    assert e.field_seconds > 0 and e.guidance_seconds == 0.0 and e.steps == 4
    assert all(torch.equal(v, before[k]) for k, v in field.state_dict().items())
    assert all(p.grad is None for p in field.parameters())
    infos = [tr.step() for _ in range(4)]
    assert [i["steps"] for i in infos] == [4] * 4
    assert infos[-1]["eta_s"] == 0.0 and all(i["eta_s"] >= 0 for i in infos)
    assert infos[1]["eta_s"] == pytest.approx(2 * infos[1]["seconds"])


def test_cli_prints_the_estimate_and_time_left(tmp_path, capsys, monkeypatch):
    import repaint_nerf.app.commands.repaint as cmd
    from repaint_nerf.app.cli import main
    from repaint_nerf.core.train.checkpoint import Checkpoint
    from repaint_nerf.core.train.header import CheckpointHeader
    from repaint_nerf.core.workspace.workspace import Workspace

    scene, masks = make_scene()
    field = make_field()
    ws = Workspace.create(tmp_path / "ws")
    monkeypatch.setattr(cmd, "open_workspace",
                        lambda path, device=None: (ws, scene, field, make_grid(field), masks, 96))
    assert main(["repaint", str(ws.root), "--guidance", "recolor", "--prompt", "make it blue", "--steps", "3"]) == 0
    out = capsys.readouterr().out
    assert "estimated time:" in out and "3 steps x" in out and "timed on this device" in out
    assert "step 3/3" in out and " left)" in out
    # the edit marched at the field's own budget, and its version renders at it (not the renderer's 1024)
    header = CheckpointHeader.from_dict(Checkpoint.load(ws.version_path(ws.current_version)).header)
    assert header.kind == "edit" and header.max_samples == 96
    assert main(["repaint", str(ws.root), "--guidance", "sd", "--prompt", "x", "--sds-resolution", "100"]) == 2
    assert "multiple of 64" in capsys.readouterr().err


def test_repaint_panel_estimate_uses_the_chosen_guidance_steps_and_device():
    from types import SimpleNamespace

    from repaint_nerf.app.panels.repaint import _estimate
    from repaint_scene import make_cameras

    cams = make_cameras(size=16)
    from repaint_nerf.core.repaint.config import RepaintConfig

    state = SimpleNamespace(backend="sd", repaint_config=RepaintConfig(steps=200),
                            scene_info={"cameras": cams, "device": "cpu"})
    app = SimpleNamespace(state=state, cache={})
    text = _estimate(app)
    want = estimate_before_start("sd", 200, 16, 16, CPU).describe()
    assert text == want and "200 steps" in text and "bench sdcost" in text
    state.backend, state.repaint_config.steps = "recolor", 10
    assert _estimate(app) == estimate_before_start("recolor", 10, 16, 16, CPU).describe() != text
