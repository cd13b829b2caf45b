"""Stable Diffusion speed options on the tiny pipeline: the bf16 UNet's guidance gradient against fp32's, a
tiny autoencoder (TAESD-style) loaded from a folder or the local cache that trains the field, score
distillation at a lower resolution, and their bad input."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from repaint_nerf.core.errors import ModelNotFoundError, UserError
from repaint_nerf.core.models.sd import load_stable_diffusion
from repaint_nerf.core.models.sd_speed import apply_speed_options, cpu_has_bf16, set_channels_last, unet_dtype
from repaint_nerf.core.repaint.sds import SDSGuidance
from repaint_scene import make_field, make_grid, make_scene
from tiny_diffusion import cached

# Cosine between the bf16 and fp32 UNets' image gradients on the tiny pipeline at guidance scale 100:
# measured 0.993-0.998 over seeds 0-7, norm ratio 0.985-1.033 (classifier-free guidance multiplies the
# UNet's rounding by 100).
BF16_COSINE_BAR = 0.98


def make_tiny_autoencoder(folder, latent_channels: int = 4, seed: int = 0):
    """A diffusers AutoencoderTiny (TAESD layout, 1/8 scale) with tiny random weights, saved to `folder`."""
    from diffusers import AutoencoderTiny

    torch.manual_seed(seed)
    ae = AutoencoderTiny(encoder_block_out_channels=(4, 4, 4, 4), decoder_block_out_channels=(4, 4, 4, 4),
                         num_encoder_blocks=(1, 1, 1, 1), num_decoder_blocks=(1, 1, 1, 1),
                         latent_channels=latent_channels)
    ae.save_pretrained(folder)
    return folder


@pytest.fixture()
def sd(tmp_path_factory):
    return load_stable_diffusion(cached("sd", tmp_path_factory))


def _image_grad(sd, seed: int, **kw) -> torch.Tensor:
    img = torch.rand(1, 3, 64, 64, generator=torch.Generator().manual_seed(100 + seed)).requires_grad_(True)
    out = SDSGuidance(sd, "a blue rose", seed=seed, **kw).loss(img, None, 0, 0)
    assert not out["skipped"] and out["loss"].dtype == torch.float32
    out["loss"].backward()
    return img.grad.detach().double().flatten()


def test_unet_precision_names():
    cpu = torch.device("cpu")
    assert unet_dtype("auto", cpu) == (torch.bfloat16 if cpu_has_bf16() else torch.float32)
    assert unet_dtype("fp32", cpu) == torch.float32 and unet_dtype("bf16", cpu) == torch.bfloat16
    with pytest.raises(UserError, match="CUDA"):
        unet_dtype("fp16", cpu)
    with pytest.raises(UserError, match="precision"):
        unet_dtype("int8", cpu)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_bf16_unet_gradient_close_to_fp32(sd, seed):
    ref = _image_grad(sd, seed)
    sd.set_unet_dtype(torch.bfloat16)
    assert sd.unet_dtype == torch.bfloat16 and sd.vae.dtype == torch.float32  # only the UNet changes
    got = _image_grad(sd, seed)
    cos = float(torch.nn.functional.cosine_similarity(ref, got, dim=0))
    assert torch.isfinite(got).all() and cos > BF16_COSINE_BAR, cos
    assert 0.9 < float(got.norm() / ref.norm()) < 1.1


def test_tiny_autoencoder_replaces_the_vae_encoder_and_trains(sd, tmp_path, monkeypatch):
    folder = make_tiny_autoencoder(tmp_path / "taesd")
    apply_speed_options(sd, "fp32", folder)
    assert sd.tiny_vae is not None
    monkeypatch.setattr(sd.vae, "encode", lambda *a, **k: pytest.fail("the VAE encoder ran"))
    lat = sd.encode_images(torch.rand(1, 3, 64, 64))
    assert lat.shape == (1, 4, 8, 8)
    monkeypatch.undo()

    scene, masks = make_scene()
    field = make_field()
    from repaint_nerf.core.repaint.trainer import RepaintTrainer

    tr = RepaintTrainer(scene, field, make_grid(field), masks=masks, guidance="sd", prompt="a blue ball",
                        sd_path=sd.path, steps=3, max_samples=256, lambda_clip=0.0,  # no CLIP: this tests the SD path
                        sd_tiny_autoencoder=str(folder), sd_unet_precision="bf16")
    assert tr.guidance.sd.tiny_vae is not None and tr.guidance.sd.unet_dtype == torch.bfloat16
    conv = tr.guidance.sd.unet.conv_in.weight
    assert conv.is_contiguous(memory_format=torch.channels_last) and not conv.is_contiguous()  # the default
    ae_conv = tr.guidance.sd.tiny_vae.encoder.layers[0].weight
    assert ae_conv.is_contiguous(memory_format=torch.channels_last) and not ae_conv.is_contiguous()
    before = field.col.detach().clone()
    infos = [tr.step() for _ in range(3)]
    assert all(not i["skipped"] and np.isfinite(i["loss"]) for i in infos)
    assert not torch.equal(before, field.col.detach())
    assert all(p.grad is None for p in tr.guidance.sd.tiny_vae.parameters())


def test_channels_last_tiny_autoencoder_gives_the_same_latents_and_gradient(sd, tmp_path):
    apply_speed_options(sd, "fp32", make_tiny_autoencoder(tmp_path / "ae"), channels_last=False)
    outs = []
    for on in (False, True):
        set_channels_last(sd, on)
        x = torch.rand(1, 3, 64, 64, generator=torch.Generator().manual_seed(0)).requires_grad_(True)
        lat = sd.encode_images(x)
        (lat * torch.linspace(-1, 1, lat.numel()).view(lat.shape)).sum().backward()
        outs.append((lat.detach(), x.grad))
    w = sd.tiny_vae.encoder.layers[0].weight
    assert w.is_contiguous(memory_format=torch.channels_last) and not w.is_contiguous()
    torch.testing.assert_close(outs[1][0], outs[0][0], atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(outs[1][1], outs[0][1], atol=1e-6, rtol=1e-4)


def test_tiny_autoencoder_from_the_local_cache_without_network(tmp_path, monkeypatch):
    from repaint_nerf.core.models.taesd import load_tiny_autoencoder

    snap = tmp_path / "hf" / "hub" / "models--someone--taesd-tiny" / "snapshots" / "abc123"
    make_tiny_autoencoder(snap)
    (snap.parents[1] / "refs").mkdir()
    (snap.parents[1] / "refs" / "main").write_text("abc123")
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf"))
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "hf" / "hub"))
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    ae = load_tiny_autoencoder("someone/taesd-tiny", torch.device("cpu"))
    assert int(ae.config.latent_channels) == 4 and not any(p.requires_grad for p in ae.parameters())
    with pytest.raises(ModelNotFoundError, match="tiny autoencoder") as exc:
        load_tiny_autoencoder("someone/not-there", torch.device("cpu"))
    assert "madebyollin/taesd" in exc.value.hint


def test_tiny_autoencoder_bad_input(sd, tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(ModelNotFoundError, match="config.json"):
        apply_speed_options(sd, "fp32", tmp_path / "empty")
    with pytest.raises(UserError, match="3-channel latents"):
        apply_speed_options(sd, "fp32", make_tiny_autoencoder(tmp_path / "ae3", latent_channels=3))


def test_low_resolution_sds_shapes(sd, monkeypatch):
    seen = {}
    real = sd.predict_noise

    def spy(latents, t, emb):
        seen["latents"] = tuple(latents.shape)
        return real(latents, t, emb)

    monkeypatch.setattr(sd, "predict_noise", spy)
    g = SDSGuidance(sd, "a rose", seed=0, sds_resolution=32)
    img = torch.rand(1, 3, 48, 40, requires_grad=True)
    out = g.loss(img, None, 0, 0)
    out["loss"].backward()
    assert seen["latents"] == (2, 4, 4, 4)  # 32 px / 8 = 4 latent cells, [uncond, cond]
    assert img.grad.shape == img.shape and torch.isfinite(img.grad).all() and img.grad.abs().sum() > 0
    g.loss(torch.rand(1, 3, 48, 40), None, 0, 0)
    SDSGuidance(sd, "a rose", sds_resolution=None).loss(torch.rand(1, 3, 16, 16), None, 0, 0)
    assert seen["latents"] == (2, 4, 8, 8)  # default: the model's own 64 px
    for bad in (24, 8, 0):
        with pytest.raises(UserError, match="multiple of 16"):
            SDSGuidance(sd, "a rose", sds_resolution=bad)


def test_profile_records_each_stage(sd):
    g = SDSGuidance(sd, "a rose", seed=0, profile=True)
    g.loss(torch.rand(1, 3, 16, 16, requires_grad=True), None, 0, 0)
    assert set(g.stage_seconds) == {"resize", "encode_forward", "unet_forward", "loss"}
    assert all(v >= 0 for v in g.stage_seconds.values())


def test_annealed_timesteps_fall_linearly_and_uniform_stays():
    from repaint_nerf.core.repaint.guidance import TimestepSampler

    ab = torch.linspace(0.999, 0.01, 1000)
    uni = TimestepSampler(ab, (0.02, 0.98), torch.Generator().manual_seed(0))
    ann = TimestepSampler(ab, (0.02, 0.98), torch.Generator().manual_seed(0), "annealed")
    assert uni.upper(0.0) == uni.upper(1.0) == 980
    assert (ann.upper(0.0), ann.upper(0.5), ann.upper(1.0)) == (980, 740, 500)
    late = [ann.sample(0.9) for _ in range(200)]
    assert min(late) >= 20 and max(late) <= ann.upper(0.9) == 548
    assert max(late) > 450  # still spans the range below the bound
    with pytest.raises(ValueError, match="schedule"):
        TimestepSampler(ab, (0.02, 0.98), None, "cosine")


def test_sds_passes_progress_to_the_annealed_schedule(sd):
    g = SDSGuidance(sd, "a rose", seed=0, t_schedule="annealed", total_steps=10)
    ts = [g.loss(torch.rand(1, 3, 16, 16), None, 0, 9)["t"] for _ in range(20)]
    assert max(ts) <= g.sampler.upper(0.9) < 980
