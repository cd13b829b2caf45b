"""Offline edits: colour names, recolour and inpaint math, and recolour/remove through the repaint trainer."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from repaint_nerf.core.errors import UserError
from repaint_nerf.core.repaint.color_space import lab_to_rgb, linear_to_srgb, luminance, rgb_to_lab, srgb_to_linear
from repaint_nerf.core.repaint.colors import COLORS, color_in_prompt, parse_rgb, resolve_color
from repaint_nerf.core.repaint.inpaint import inpaint
from repaint_nerf.core.repaint.recolor import recolor
from repaint_nerf.core.repaint.region import region_points, selection_region
from repaint_nerf.core.repaint.registry import offline_kind
from repaint_nerf.core.repaint.trainer import RepaintTrainer
from repaint_scene import make_field, make_grid, make_scene


def test_colour_names_in_prompts():
    assert resolve_color("make it blue") == COLORS["blue"]
    assert color_in_prompt("a light blue vase")[0] == "light blue"
    assert color_in_prompt("turn the red ball green")[0] == "green"
    assert color_in_prompt("bluetooth speaker") is None  # whole words only
    assert resolve_color("whatever", "30,80,230") == pytest.approx((30 / 255, 80 / 255, 230 / 255))
    assert parse_rgb("0.1,0.2,0.3") == pytest.approx((0.1, 0.2, 0.3))
    assert parse_rgb("#ff0000") == pytest.approx((1.0, 0.0, 0.0))
    with pytest.raises(UserError, match="--color"):
        resolve_color("a nice vase")
    with pytest.raises(UserError):
        parse_rgb("300,0,0")
    assert offline_kind("remove the ball") == "remove" and offline_kind("make it blue") == "recolor"


def _hue(rgb: torch.Tensor) -> torch.Tensor:
    lab = rgb_to_lab(rgb)
    return torch.atan2(lab[..., 2], lab[..., 1])


def test_recolour_keeps_shading_and_takes_the_hue():
    shade = torch.linspace(0.2, 1.0, 9)[:, None]
    red = linear_to_srgb(srgb_to_linear(torch.tensor([0.85, 0.12, 0.10])) * shade)
    blue = torch.tensor(COLORS["blue"])
    out = recolor(red, blue, mode="shading", ref_luminance=float(luminance(red).max()))
    # same luminance ratios as the input (shading kept), hue of the target
    ratio_in = luminance(red) / luminance(red).max()
    ratio_out = luminance(out) / luminance(out).max()
    torch.testing.assert_close(ratio_out, ratio_in, atol=2e-3, rtol=0)
    assert torch.allclose(_hue(out), _hue(blue).expand(9), atol=0.05)
    torch.testing.assert_close(out[-1], blue, atol=2e-3, rtol=0)  # the brightest pixel gets the target
    light = recolor(red, blue, mode="lightness")
    in_gamut = (light.amax(-1) < 0.999) & (light.amin(-1) > 0.001)
    assert in_gamut.any()
    torch.testing.assert_close(rgb_to_lab(light)[in_gamut, 0], rgb_to_lab(red)[in_gamut, 0],
                               atol=0.5, rtol=0)
    # outside the mask nothing changes
    m = torch.zeros(9)
    m[:3] = 1
    part = recolor(red, blue, m)
    torch.testing.assert_close(part[3:], red[3:])


def test_lab_round_trip_and_inpaint():
    x = torch.rand(64, 3)
    torch.testing.assert_close(lab_to_rgb(rgb_to_lab(x)), x, atol=1e-4, rtol=0)
    img = torch.zeros(20, 20, 3)
    img[..., 1] = 0.6
    img[8:12, 8:12] = torch.tensor([1.0, 0.0, 0.0])
    hole = torch.zeros(20, 20)
    hole[7:13, 7:13] = 1
    out = inpaint(img, hole)
    assert torch.allclose(out[8:12, 8:12], torch.tensor([0.0, 0.6, 0.0]), atol=0.02)
    torch.testing.assert_close(out[hole == 0], img[hole == 0])


def test_selection_region_is_the_visual_hull():
    scene, masks = make_scene()
    cams = scene.field_cameras("train")
    region = selection_region(cams, [torch.from_numpy(m).float() for m in masks], 1.0, 16)
    ax = (torch.arange(16) + 0.5) / 8 - 1
    x = torch.stack(torch.meshgrid(ax, ax, ax, indexing="ij"), -1)
    assert region[x.norm(dim=-1) < 0.2].all()  # the ball's core
    assert not region[x[..., 2] < -0.5].any()  # nothing of the slab below it


@pytest.fixture(scope="module")
def scene():
    return make_scene(size=20)


def _run(scene, masks, kind, steps, **kw):
    field = make_field()
    tr = RepaintTrainer(scene, field, make_grid(field), masks=masks, guidance=kind, steps=steps, optimizer="official", lr=0.05,
                        max_samples=256, **kw)
    before = tr.evaluate("train", masks)
    tr.run()
    return tr, before, tr.evaluate("train", masks)


def test_recolour_edit_changes_the_hue_and_keeps_the_rest(scene):
    scene, masks = scene
    tr, before, after = _run(scene, masks, "recolor", 30, prompt="make it blue")
    assert tr.kind == "recolor" and tr.skipped_steps == 0
    rgb = torch.cat([tr.render_view(i, grad=False)[0].permute(1, 2, 0)[torch.from_numpy(m)]
                     for i, m in enumerate(masks)])
    mean = rgb.mean(0)
    assert mean[2] > mean[0] + 0.1, f"the ball should turn blue, mean colour {mean.tolist()}"
    assert after["psnr_unmasked"] > 25.0 and after["psnr_unmasked"] > before["psnr_unmasked"] - 2.0


def test_remove_edit_clears_the_object(scene):
    scene, masks = scene
    tr, before, after = _run(scene, masks, "remove", 30, prompt="remove the ball")
    assert tr.kind == "remove" and tr.region is None  # a removal never marks new cells occupied
    red = []
    for i, m in enumerate(masks):
        rgb = tr.render_view(i, grad=False)[0].permute(1, 2, 0)[torch.from_numpy(m)]
        red.append((rgb[:, 0] - rgb[:, 1:].mean(-1)).mean())
    assert float(torch.stack(red).mean()) < 0.15, "the red ball's pixels should show the slab or background"
    region = tr.guidance.region
    x = region_points(region, 1.0, 2048, torch.Generator().manual_seed(1))
    with torch.no_grad():
        assert float(tr.field.density(x).mean()) < 0.2 * float(make_field().density(x).mean())
    assert after["psnr_unmasked"] > 25.0
