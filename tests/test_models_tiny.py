"""Model path resolution and the SD / CLIP loaders, on tiny random-weight models saved like real ones."""
from __future__ import annotations

import shutil

import pytest
import torch

from repaint_nerf.core.errors import ModelNotFoundError
from repaint_nerf.core.models.clip import load_clip
from repaint_nerf.core.models.paths import resolve_model_path
from repaint_nerf.core.models.sd import load_stable_diffusion
from tiny_diffusion import MAX_LEN, cached


@pytest.fixture(scope="module")
def sd_path(tmp_path_factory):
    return cached("sd", tmp_path_factory)


@pytest.fixture(scope="module")
def clip_path(tmp_path_factory):
    return cached("clip", tmp_path_factory)


def test_resolution_order_flag_env_root_settings(tmp_path):
    dirs = {n: (tmp_path / n) for n in ("flag", "env", "root", "settings")}
    for d in dirs.values():
        d.mkdir()
    (dirs["root"] / "sd").mkdir()
    env = {"REPAINT_NERF_SD_PATH": str(dirs["env"]), "REPAINT_NERF_MODELS": str(dirs["root"])}
    settings = {"sd_path": str(dirs["settings"])}
    assert resolve_model_path("sd", dirs["flag"], settings, env) == dirs["flag"]
    assert resolve_model_path("sd", None, settings, env) == dirs["env"]
    env.pop("REPAINT_NERF_SD_PATH")
    assert resolve_model_path("sd", None, settings, env) == dirs["root"] / "sd"
    env.pop("REPAINT_NERF_MODELS")
    assert resolve_model_path("sd", None, settings, env) == dirs["settings"]
    assert resolve_model_path("clip", None, {"models": {"clip": str(dirs["flag"])}}, env) == dirs["flag"]


@pytest.mark.parametrize("kind,flag,var", [("sd", "--sd-path", "REPAINT_NERF_SD_PATH"),
                                           ("clip", "--clip-path", "REPAINT_NERF_CLIP_PATH")])
def test_missing_model_names_flag_and_env_var(tmp_path, kind, flag, var):
    with pytest.raises(ModelNotFoundError) as nothing:
        resolve_model_path(kind, None, None, environ={})
    with pytest.raises(ModelNotFoundError) as absent:
        resolve_model_path(kind, None, None, environ={var: str(tmp_path / "nope")})
    for err in (nothing, absent):
        assert flag in str(err.value) and var in str(err.value)
    assert str(tmp_path / "nope") in str(absent.value)


def test_sd_folder_loads_frozen_with_model_resolution(sd_path, monkeypatch):
    monkeypatch.setenv("REPAINT_NERF_SD_PATH", str(sd_path))
    sd = load_stable_diffusion(resolve_model_path("sd"))
    assert sd.dtype == torch.float32 and sd.device.type == "cpu"
    assert sd.resolution == 64 and sd.vae_scale_factor == 8 and sd.num_train_timesteps == 1000
    assert sd.latent_scale == pytest.approx(0.18215)
    for m in (sd.unet, sd.vae, sd.text_encoder):
        assert not m.training and not any(p.requires_grad for p in m.parameters())
    emb = sd.encode_text(["a blue rose in leaves", ""])
    assert emb.shape == (2, MAX_LEN, 16) and torch.isfinite(emb).all()
    assert not torch.allclose(emb[0], emb[1])
    z = sd.encode_images(torch.rand(1, 3, 64, 64, requires_grad=True))
    assert z.shape == (1, 4, 8, 8) and z.requires_grad


def test_sd_folder_missing_component_is_clear(sd_path, tmp_path):
    broken = tmp_path / "broken-sd"
    shutil.copytree(sd_path, broken)
    shutil.rmtree(broken / "unet")
    with pytest.raises(ModelNotFoundError, match=r"missing unet/") as err:
        load_stable_diffusion(broken)
    assert str(broken) in str(err.value)


def test_sd_rejects_non_checkpoint_file(tmp_path):
    f = tmp_path / "model.bin"
    f.write_bytes(b"\0")
    with pytest.raises(ModelNotFoundError, match=r"\.safetensors or \.ckpt"):
        load_stable_diffusion(f)


def test_clip_folder_loads(clip_path):
    clip = load_clip(clip_path)
    assert clip.image_size == 32 and len(clip.mean) == 3
    txt = clip.encode_text(["leaves", "a blue rose"])
    img = clip.encode_image(torch.randn(2, 3, 32, 32))
    assert txt.shape == (2, 8) and img.shape == (2, 8)
    assert not any(p.requires_grad for p in clip.model.parameters())


def test_clip_folder_without_config_is_clear(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(ModelNotFoundError, match="config.json is missing"):
        load_clip(tmp_path / "empty")
    with pytest.raises(ModelNotFoundError, match="--clip-path"):
        load_clip(tmp_path / "absent")


def test_build_guidance_sd_through_settings(sd_path, monkeypatch):
    from repaint_nerf.core.repaint import Guidance, build_guidance

    for var in ("REPAINT_NERF_SD_PATH", "REPAINT_NERF_MODELS"):
        monkeypatch.delenv(var, raising=False)
    with pytest.raises(ModelNotFoundError, match="--sd-path"):
        build_guidance("sd", prompt="a rose")
    g = build_guidance("sd", prompt="a rose", settings={"sd_path": str(sd_path)}, seed=0)
    assert isinstance(g, Guidance)
