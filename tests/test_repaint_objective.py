"""The stage-2 objective (paper Eq. unmask, Eq. s2) and the options that shape it, each against its written
formula: the sum and mean reductions, the unmask margin, the optimiser presets' learning-rate schedules."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from repaint_nerf.core.errors import UserError
from repaint_nerf.core.repaint.objective import stage2_loss, unmask_loss, unmask_weight
from repaint_nerf.core.repaint.trainer import RepaintTrainer
from repaint_scene import make_field, make_grid, make_scene


@pytest.fixture(scope="module")
def scene():
    return make_scene()


def _trainer(scene, guidance="recolor", **kw):
    scene, masks = scene
    field = make_field()
    kw.setdefault("max_samples", 256)
    kw.setdefault("prompt", "blue")
    return RepaintTrainer(scene, field, make_grid(field), masks=masks, guidance=guidance, **kw)


def _reference_unmask(rgb: np.ndarray, target: np.ndarray, mask: np.ndarray) -> tuple[float, float]:
    """Eq. unmask written out per pixel: sum_r ||C(r) 1(m<0.5) - C^(r) 1(m<0.5)||^2, and the official code's
    mean of the squared, mask-zeroed image over all of its 3 H W values."""
    h, w = mask.shape
    total = 0.0
    for y in range(h):
        for x in range(w):
            keep = 1.0 if mask[y, x] < 0.5 else 0.0
            total += sum((rgb[c, y, x] * keep - target[c, y, x] * keep) ** 2 for c in range(3))
    return total, total / (3 * h * w)


def test_unmask_loss_sum_and_mean_match_the_written_formulas():
    g = torch.Generator().manual_seed(0)
    rgb, target = torch.rand(1, 3, 7, 9, generator=g), torch.rand(1, 3, 7, 9, generator=g)
    mask = torch.rand(7, 9, generator=g)  # soft values: 1(mask < 0.5) decides
    keep = (mask < 0.5).float()[None, None]
    want_sum, want_mean = _reference_unmask(rgb[0].double().numpy(), target[0].double().numpy(), mask.numpy())
    assert float(unmask_loss(rgb, target, keep, "sum")) == pytest.approx(want_sum, rel=1e-5)
    assert float(unmask_loss(rgb, target, keep, "mean")) == pytest.approx(want_mean, rel=1e-5)
    with pytest.raises(ValueError, match="reduction"):
        unmask_loss(rgb, target, keep, "max")


def test_stage2_loss_is_the_weighted_sum():
    g, u, c = torch.tensor(0.7), torch.tensor(0.2), torch.tensor(-0.9)
    assert float(stage2_loss(g, u, 10.0)) == pytest.approx(0.7 + 10.0 * 0.2)
    assert float(stage2_loss(g, u, 10.0, c, 0.01)) == pytest.approx(0.7 + 10.0 * 0.2 + 0.01 * -0.9)


def test_unmask_weight_ramps_linearly_then_holds():
    """lambda(p) = lambda * (start + (1 - start) * min(1, p / ramp)), written as the two straight pieces."""
    lam, ramp, start = 5.0, 0.5, 0.2
    for p in np.linspace(0.0, 1.0, 11):
        want = lam * start + (lam - lam * start) * (p / ramp) if p < ramp else lam
        assert unmask_weight(lam, float(p), ramp, start) == pytest.approx(want, rel=1e-12)
    assert unmask_weight(lam, 0.0, 0.0, start) == lam  # ramp 0: the paper's constant weight
    assert unmask_weight(0.0, 0.1, ramp, start) == 0.0  # no weight stays no weight


def test_trainer_ramps_the_unmask_weight_over_the_steps(scene):
    steps = 4
    tr = _trainer(scene, ConstantGuidance(), steps=steps, lambda_unmask=8.0, unmask_ramp=0.5, unmask_ramp_start=0.25)
    infos = [tr.step() for _ in range(steps)]
    # steps 0..3 of 4 at progress 0, 1/4, 1/2, 3/4: 8 x 0.25, halfway up, then the full weight
    want = [2.0, 5.0, 8.0, 8.0]
    assert [i["lambda_unmask"] for i in infos] == pytest.approx(want)
    for i, lam in zip(infos, want):  # and that weight is the one in Eq. s2's loss
        assert i["loss"] == pytest.approx(i["guidance"] + lam * i["unmask"], rel=1e-5)
    with pytest.raises(UserError, match="unmask_ramp"):
        _trainer(scene, steps=1, unmask_ramp=1.5)


class ConstantGuidance:
    """A guidance whose loss is a known function of the render: 0.5 * sum(rgb)."""

    def loss(self, rgb, mask, view, step):
        return {"loss": 0.5 * rgb.float().sum(), "skipped": False, "t": 0, "grad_norm": 0.0}


@pytest.mark.parametrize("reduction", ["sum", "mean"])
def test_trainer_step_is_eq_s2_on_the_view_it_rendered(scene, reduction, monkeypatch):
    tr = _trainer(scene, ConstantGuidance(), steps=3, lambda_unmask=7.0, unmask_reduction=reduction,
                  unmask_margin=0, perturb=False, unmask_ramp=0.0)
    seen = {}
    real = tr.render_view
    monkeypatch.setattr(tr, "render_view",
                        lambda v, grad=True, pause=None: seen.setdefault("rgb", real(v, grad, pause)))
    info = tr.step()
    rgb = seen["rgb"].detach()[0].double().numpy()
    target = tr.images[info["view"]].permute(2, 0, 1).double().numpy()
    s, m = _reference_unmask(rgb, target, tr.masks[info["view"]].numpy())
    want_unmask = s if reduction == "sum" else m
    assert info["unmask"] == pytest.approx(want_unmask, rel=1e-4)
    assert info["loss"] == pytest.approx(0.5 * rgb.sum() + 7.0 * want_unmask, rel=1e-4)


def test_unmask_margin_frees_a_square_ring_around_the_mask(scene):
    exact = _trainer(scene, steps=1, unmask_margin=0)
    ring = _trainer(scene, steps=1, unmask_margin=2)
    for m, k0, k2 in zip(exact.masks, exact.keep, ring.keep):
        m = m.numpy() > 0.5
        torch.testing.assert_close(k0, torch.from_numpy((~m).astype(np.float32)))  # the paper's 1(mask < 0.5)
        h, w = m.shape
        near = np.zeros_like(m)
        for y, x in zip(*np.nonzero(m)):  # every pixel within 2 px (Chebyshev) of a masked one
            near[max(0, y - 2):y + 3, max(0, x - 2):x + 3] = True
        torch.testing.assert_close(k2, torch.from_numpy((~near).astype(np.float32)))
    with pytest.raises(UserError, match="unmask_margin"):
        _trainer(scene, steps=1, unmask_margin=-1)


@pytest.mark.parametrize("preset,base,grid_mult", [("paper", 1e-3, 1.0), ("official", 5e-3, 10.0)])
def test_optimizer_presets_decay_by_a_tenth_over_the_edit(scene, preset, base, grid_mult):
    """lr(step k of n) = base x multiplier x 0.1^(k / n): the official code's schedule, the paper's 1e-3 -> 1e-4."""
    steps = 5
    tr = _trainer(scene, steps=steps, optimizer=preset)
    for k in range(steps):
        tr.step()
        lrs = {g["name"]: g["lr"] for g in tr.optimizer.param_groups}
        assert lrs["grid"] == pytest.approx(base * grid_mult * 0.1 ** (k / steps), rel=1e-9)
