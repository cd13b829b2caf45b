"""Guidance backends: SDS on tiny SD parts, the analytic denoiser, the CLIP background loss, the loss form, and
the registry that lists the backends (with the protocol's optional extras)."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from repaint_nerf.core.models.sd import load_stable_diffusion
from repaint_nerf.core.repaint.analytic import AnalyticGuidance, sd_alphas_cumprod
from repaint_nerf.core.repaint.clip_loss import ClipBackgroundLoss, build_clip_loss, clip_preprocess
from repaint_nerf.core.repaint.guidance import TimestepSampler, distillation_loss
from repaint_nerf.core.repaint.sds import SDSGuidance
from repaint_nerf.core.train.adan import Adan
from tiny_diffusion import cached


@pytest.fixture(scope="module")
def sd(tmp_path_factory):
    return load_stable_diffusion(cached("sd", tmp_path_factory))


@pytest.fixture(scope="module")
def clip_path(tmp_path_factory):
    return cached("clip", tmp_path_factory)


def _frozen_have_no_grad(*modules) -> bool:
    return all(not p.requires_grad and p.grad is None for m in modules for p in m.parameters())


def test_distillation_loss_gradient_equals_guidance_gradient():
    z = torch.randn(1, 4, 8, 8, requires_grad=True)
    g = torch.randn(1, 4, 8, 8)
    out = distillation_loss(z, g, t=500)
    out["loss"].backward()
    assert out["loss"].dtype == torch.float32 and not out["skipped"]
    torch.testing.assert_close(z.grad, g)
    assert out["grad_norm"] == pytest.approx(float(g.norm()), rel=1e-5)


def test_distillation_loss_clips_and_skips():
    z = torch.randn(1, 3, 4, 4, requires_grad=True)
    g = torch.full((1, 3, 4, 4), 5.0)
    distillation_loss(z, g, t=1, clip_value=1.0)["loss"].backward()
    torch.testing.assert_close(z.grad, torch.ones_like(z))
    out = distillation_loss(z, g, t=1, clip_norm=2.0)
    assert out["grad_norm"] == pytest.approx(2.0, rel=1e-4)
    g[0, 0, 0, 0] = float("nan")
    bad = distillation_loss(z, g, t=1)
    assert bad["skipped"] and bad["loss"].item() == 0.0 and not bad["loss"].requires_grad


def test_timesteps_in_official_range_and_weight():
    ab = sd_alphas_cumprod()
    s = TimestepSampler(ab, (0.02, 0.98), torch.Generator().manual_seed(0))
    ts = [s.sample() for _ in range(2000)]
    assert min(ts) >= 20 and max(ts) <= 980 and min(ts) < 40 and max(ts) > 960
    assert s.weight(500) == pytest.approx(1 - float(ab[500]))


def test_sd_schedule_matches_diffusers():
    from diffusers import DDPMScheduler

    ref = DDPMScheduler(num_train_timesteps=1000, beta_schedule="scaled_linear", beta_start=0.00085,
                        beta_end=0.012).alphas_cumprod
    torch.testing.assert_close(sd_alphas_cumprod(), ref.float(), rtol=1e-5, atol=1e-6)


def test_sds_step_end_to_end(sd):
    img = torch.nn.Parameter(torch.rand(1, 3, 24, 24))
    g = SDSGuidance(sd, "a blue rose in leaves", seed=0)
    out = g.loss(img, torch.zeros(1, 1, 24, 24), view=0, step=0)
    assert not out["skipped"] and 20 <= out["t"] <= 980 and out["grad_norm"] > 0
    assert out["loss"].dtype == torch.float32 and out["loss"].dim() == 0
    out["loss"].backward()
    assert img.grad is not None and torch.isfinite(img.grad).all() and img.grad.abs().sum() > 0
    assert _frozen_have_no_grad(sd.unet, sd.vae, sd.text_encoder)


def test_sds_classifier_free_guidance_and_weight(sd, monkeypatch):
    """grad = w(t) (eps_u + s (eps_c - eps_u) - eps), with [uncond, cond] embeddings and the model resolution."""
    g = SDSGuidance(sd, "a rose", negative_prompt="", guidance_scale=7.0, seed=1)
    noise = torch.randn(1, 4, 8, 8).to(sd.device)
    eps_u, eps_c = torch.randn(1, 4, 8, 8).to(sd.device), torch.randn(1, 4, 8, 8).to(sd.device)
    seen = {}

    def fake_unet(latents, t, emb):
        seen.update(latents=latents, t=t, emb=emb)
        return torch.cat([eps_u, eps_c])

    monkeypatch.setattr(g, "_noise", lambda like: noise)
    monkeypatch.setattr(sd, "predict_noise", fake_unet)
    out = g.loss(torch.rand(1, 3, 24, 24, requires_grad=True), None, 0, 0)
    t = out["t"]
    expected = (1 - float(sd.alphas_cumprod[t])) * (eps_u + 7.0 * (eps_c - eps_u) - noise)
    assert out["grad_norm"] == pytest.approx(float(expected.norm()), rel=1e-5)
    assert out["loss"].item() == pytest.approx(0.5 * float(expected.pow(2).sum()), rel=1e-5)
    assert seen["latents"].shape == (2, 4, 8, 8) and seen["t"].tolist() == [t, t]
    torch.testing.assert_close(seen["emb"], torch.cat([sd.encode_text([""]), sd.encode_text(["a rose"])]))


@pytest.mark.parametrize("prediction_type", ["epsilon", "v_prediction"])
def test_sds_reads_the_model_prediction_type(sd, monkeypatch, prediction_type):
    """A UNet that predicts its target exactly gives zero SDS gradient, whether it predicts the noise or v.

    The reference targets come from diffusers' scheduler (add_noise / get_velocity), not from sds.py:
    v = sqrt(abar) eps - sqrt(1 - abar) x0, so reading v as eps (the old bug) leaves a non-zero gradient."""
    from diffusers import DDIMScheduler

    monkeypatch.setattr(sd, "scheduler", DDIMScheduler.from_config(sd.scheduler.config,
                                                                   prediction_type=prediction_type))
    assert sd.prediction_type == prediction_type
    g = SDSGuidance(sd, "a rose", guidance_scale=3.0, seed=2)
    x0 = torch.randn(1, 4, 8, 8)
    noise = torch.randn(1, 4, 8, 8)
    monkeypatch.setattr(g, "_noise", lambda like: noise)
    monkeypatch.setattr(sd, "encode_images", lambda x, gen=None: x0 + 0 * x.mean())

    def exact_unet(latents, t, emb):
        target = noise if prediction_type == "epsilon" else sd.scheduler.get_velocity(x0, noise, t[:1])
        return target.repeat(2, 1, 1, 1)

    monkeypatch.setattr(sd, "predict_noise", exact_unet)
    out = g.loss(torch.rand(1, 3, 16, 16, requires_grad=True), None, 0, 0)
    assert out["grad_norm"] < 1e-4 * float(noise.norm())

    # An arbitrary v: eps from the x0 the v implies, x0_hat = sqrt(abar) x_t - sqrt(1 - abar) v,
    # eps = (x_t - sqrt(abar) x0_hat) / sqrt(1 - abar) (the DDIM step's own algebra, written out here).
    if prediction_type == "v_prediction":
        v_u, v_c = torch.randn(1, 4, 8, 8), torch.randn(1, 4, 8, 8)
        monkeypatch.setattr(sd, "predict_noise", lambda lat, t, emb: torch.cat([v_u, v_c]))
        out = g.loss(torch.rand(1, 3, 16, 16, requires_grad=True), None, 0, 0)
        ab = float(sd.alphas_cumprod[out["t"]])
        x_t = math.sqrt(ab) * x0 + math.sqrt(1 - ab) * noise

        def eps_of(v):
            x0_hat = math.sqrt(ab) * x_t - math.sqrt(1 - ab) * v
            return (x_t - math.sqrt(ab) * x0_hat) / math.sqrt(1 - ab)

        eps_hat = eps_of(v_u) + 3.0 * (eps_of(v_c) - eps_of(v_u))
        expected = (1 - ab) * (eps_hat - noise)
        assert out["grad_norm"] == pytest.approx(float(expected.norm()), rel=1e-4)


def test_sds_rejects_unknown_prediction_type(sd, monkeypatch):
    from diffusers import DDIMScheduler

    monkeypatch.setattr(sd, "scheduler", DDIMScheduler.from_config(sd.scheduler.config, prediction_type="sample"))
    with pytest.raises(ValueError, match="prediction_type"):
        SDSGuidance(sd, "a rose", seed=0).loss(torch.rand(1, 3, 16, 16, requires_grad=True), None, 0, 0)


def test_sds_prompt_embeddings_are_cached(sd, monkeypatch):
    calls = []
    real = sd.encode_text
    monkeypatch.setattr(sd, "encode_text", lambda p: calls.append(p) or real(p))
    g = SDSGuidance(sd, "a rose", seed=0)
    for step in range(3):
        g.loss(torch.rand(1, 3, 16, 16, requires_grad=True), None, 0, step)
    g.set_prompt("a rose")
    assert sorted(map(tuple, calls)) == [("",), ("a rose",)]


def test_sds_non_finite_eps_is_skipped_not_applied(sd, monkeypatch):
    g = SDSGuidance(sd, "a rose", seed=0)
    monkeypatch.setattr(sd, "predict_noise", lambda lat, t, emb: torch.full_like(lat, float("nan")))
    img = torch.nn.Parameter(torch.rand(1, 3, 16, 16))
    opt = Adan([img], lr=0.1)
    before = img.detach().clone()
    out = g.loss(img, None, 0, 0)
    assert out["skipped"] and torch.isfinite(out["loss"]) and out["loss"].item() == 0.0
    assert not out["loss"].requires_grad  # nothing to backpropagate: the trainer skips the step
    torch.testing.assert_close(img.detach(), before)
    img.grad = torch.full_like(img, float("nan"))  # even if a NaN gradient got through, Adan refuses it
    opt.step()
    assert opt.skipped_steps == 1 and torch.equal(img.detach(), before)


def test_analytic_gradient_is_closed_form():
    target = torch.rand(1, 3, 8, 8)
    g = AnalyticGuidance([target], seed=0)
    img = torch.rand(1, 3, 8, 8, requires_grad=True)
    out = g.loss(img, None, view=0, step=0)
    out["loss"].backward()
    ab = float(sd_alphas_cumprod()[out["t"]])
    # d/d rgb of the [-1,1] loss: 2 * w sqrt(ab)/sqrt(1-ab) * (2 rgb - 2 x*) = 4 sqrt(ab (1 - ab)) (rgb - x*)
    expected = 4 * math.sqrt(ab * (1 - ab)) * (img.detach() - target)
    torch.testing.assert_close(img.grad, expected, rtol=1e-4, atol=1e-5)


def test_analytic_guidance_with_adan_converges_to_target():
    rng = np.random.default_rng(0)
    targets = [rng.integers(0, 256, (12, 12, 3), dtype=np.uint8) for _ in range(2)]
    g = AnalyticGuidance(targets, seed=0)
    img = torch.nn.Parameter(torch.rand(1, 3, 12, 12))
    goal = torch.from_numpy(targets[1]).float().permute(2, 0, 1)[None] / 255
    opt = Adan([img], lr=0.02, weight_decay=0.0)
    err0 = float((img.detach() - goal).norm())
    for step in range(40):
        opt.zero_grad()
        out = g.loss(img, None, view=1, step=step)
        out["loss"].backward()
        opt.step()
    assert float((img.detach() - goal).norm()) < 0.5 * err0
    assert opt.skipped_steps == 0


def test_clip_loss_differentiable_and_ignores_masked_pixels(clip_path):
    loss_fn = ClipBackgroundLoss("leaves", path=clip_path)
    img = torch.nn.Parameter(torch.rand(1, 3, 40, 48).to(loss_fn.clip.device))
    mask = torch.zeros(1, 1, 40, 48, device=loss_fn.clip.device)
    mask[..., 10:30, 12:36] = 1.0
    loss = loss_fn.loss(img, mask)
    assert loss.dtype == torch.float32 and loss.dim() == 0 and torch.isfinite(loss) and -1 <= loss.item() <= 1
    loss.backward()
    assert torch.isfinite(img.grad).all() and img.grad.abs().sum() > 0
    assert img.grad[..., 10:30, 12:36].abs().max() == 0  # blacked out: the masked region gets nothing
    cos = torch.nn.functional.cosine_similarity(
        loss_fn.clip.encode_image(clip_preprocess(img.detach() * (1 - mask), 32, loss_fn.clip.mean,
                                                  loss_fn.clip.std)),
        loss_fn.clip.encode_text(["leaves"]))
    assert loss.item() == pytest.approx(-cos.item(), abs=1e-5)


def test_clip_loss_is_lazy_and_absent_at_weight_zero(tmp_path):
    assert build_clip_loss(0.0, "leaves", path=tmp_path / "does-not-exist") is None
    lazy = build_clip_loss(0.01, "leaves", path=tmp_path / "does-not-exist")
    assert lazy is not None and not lazy.loaded
    from repaint_nerf.core.errors import ModelNotFoundError

    with pytest.raises(ModelNotFoundError, match="--clip-path"):
        lazy.loss(torch.rand(1, 3, 8, 8), torch.zeros(1, 1, 8, 8))


def test_clip_preprocess_square_is_plain_normalisation():
    img = torch.rand(2, 3, 32, 32)
    mean, std = (0.5, 0.4, 0.3), (0.2, 0.25, 0.3)
    ref = (img - torch.tensor(mean).view(1, 3, 1, 1)) / torch.tensor(std).view(1, 3, 1, 1)
    torch.testing.assert_close(clip_preprocess(img, 32, mean, std), ref)
    assert clip_preprocess(torch.rand(1, 3, 20, 60), 32, mean, std).shape == (1, 3, 32, 32)


def test_fp16_latents_gradient_goes_through_grad_scaler():
    """The official fp16 pitfall: the SDS gradient must be scaled and unscaled like any loss."""
    w = torch.nn.Parameter(torch.randn(1, 4, 8, 8))  # fp32 master weights, fp16 activations (as under AMP)
    z = w.half()
    g = torch.randn(1, 4, 8, 8)
    opt = torch.optim.SGD([w], lr=0.0)
    scaler = torch.amp.GradScaler("cpu", init_scale=1024.0)
    out = distillation_loss(z, g, t=100)
    assert out["loss"].dtype == torch.float32
    scaler.scale(out["loss"]).backward()
    torch.testing.assert_close(w.grad, 1024.0 * g, rtol=2e-3, atol=2e-3)
    scaler.unscale_(opt)
    torch.testing.assert_close(w.grad, g, rtol=2e-3, atol=2e-3)


def test_registry_records_match_the_backends_and_their_extras():
    """Each record's `extras` are the optional Guidance members its class overrides; every backend class
    satisfies the protocol; a duck-typed object with only `loss` gets the protocol's defaults."""
    from repaint_nerf.core.errors import UserError
    from repaint_nerf.core.repaint import build_guidance, registry
    from repaint_nerf.core.repaint.guidance import EXTRAS, Guidance, as_guidance
    from repaint_nerf.core.repaint.recolor import RecolorGuidance
    from repaint_nerf.core.repaint.remove import RemoveGuidance

    classes = {"recolor": RecolorGuidance, "remove": RemoveGuidance, "sd": SDSGuidance, "analytic": AnalyticGuidance}
    assert set(classes) | {"offline"} == set(registry.GUIDANCES)
    for name, cls in classes.items():
        overridden = {e for e in EXTRAS if getattr(cls, e) is not getattr(Guidance, e)}
        assert overridden == set(registry.get(name).extras), name
        assert registry.get(name).factory is not None
    assert RemoveGuidance.grow_region is False and RecolorGuidance.grow_region is False  # a recolour adds no geometry
    assert isinstance(AnalyticGuidance([torch.zeros(1, 3, 4, 4)]), Guidance)
    assert registry.resolve("offline", "remove the ball").name == "remove"
    assert registry.resolve("offline", "make it blue").name == "recolor"

    class LossOnly:
        def loss(self, rgb, mask, view, step):
            return {"loss": rgb.sum()}

    wrapped = as_guidance(LossOnly())
    assert wrapped.grow_region is True and wrapped.field_loss(None, 0) is None
    assert float(wrapped.loss(torch.ones(1, 3, 2, 2), None, 0, 0)["loss"]) == 12.0
    with pytest.raises(TypeError, match="loss"):
        as_guidance(object())
    with pytest.raises(UserError, match="use one of: offline, recolor, remove, sd, analytic"):
        registry.get("dalle")
    with pytest.raises(UserError, match="use one of"):
        build_guidance("dalle")
    with pytest.raises(UserError, match="trainer"):
        build_guidance("recolor")
