"""Stable Diffusion as users download it, offline: a diffusers folder, an original-layout single file
(.safetensors / .ckpt) and a model id in the local Hugging Face cache; the family rule, the shipped configs,
the tokenizer search and the messages for what cannot load. The network is unreachable in every test."""
from __future__ import annotations

import gzip
import json
import shutil
import socket

import pytest
import torch

from repaint_nerf.core.errors import ModelNotFoundError
from repaint_nerf.core.models import sd_single_file as sf
from repaint_nerf.core.models.paths import resolve_model_path
from repaint_nerf.core.models.sd import load_stable_diffusion
from tiny_diffusion import cached, config_only_copy, original_state_dict, save_single_file


@pytest.fixture(autouse=True)
def offline(monkeypatch, tmp_path):
    """No network: HF offline mode, an empty HF cache, and any socket connection fails the test."""
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf-home"))
    monkeypatch.delenv("HF_HUB_CACHE", raising=False)
    monkeypatch.delenv(sf.TOKENIZER_ENV, raising=False)

    def refuse(*args, **kwargs):
        raise AssertionError(f"network access attempted: {args}")

    monkeypatch.setattr(socket.socket, "connect", refuse)
    monkeypatch.setattr(socket, "create_connection", refuse)
    monkeypatch.setattr(socket, "getaddrinfo", refuse)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """(folder, single-file folder with tiny.safetensors + tiny.ckpt + tokenizer/, config-only folder)."""
    folder = cached("sd", tmp_path_factory)
    root = tmp_path_factory.mktemp("single")
    save_single_file(folder, root / "files" / "tiny.safetensors")
    save_single_file(folder, root / "files" / "tiny.ckpt")
    shutil.copytree(folder / "tokenizer", root / "files" / "tokenizer")
    return folder, root / "files", config_only_copy(folder, root / "config")


def _same_weights(a, b) -> None:
    for name in ("unet", "vae", "text_encoder"):
        sa, sb = getattr(a, name).state_dict(), getattr(b, name).state_dict()
        assert sa.keys() == sb.keys(), name
        for k in sa:
            torch.testing.assert_close(sb[k].reshape(sa[k].shape), sa[k], rtol=0, atol=0, msg=k)


@pytest.mark.parametrize("suffix", [".safetensors", ".ckpt"])
def test_single_file_loads_the_same_model_offline(tiny, suffix):
    folder, files, config = tiny
    ref = load_stable_diffusion(folder)
    sd = load_stable_diffusion(files / f"tiny{suffix}", config=config)
    _same_weights(ref, sd)
    assert sd.prediction_type == "epsilon" and sd.tokenizer.model_max_length == ref.tokenizer.model_max_length
    torch.testing.assert_close(sd.encode_text(["a blue rose"]), ref.encode_text(["a blue rose"]))


def test_single_file_uses_the_shipped_config_of_its_family(tiny, monkeypatch):
    """Without --sd-config the detected family's shipped config is used (here pointed at the tiny config,
    since a real-size SD does not fit a test); the real configs are checked against SD's layouts below."""
    folder, files, config = tiny
    monkeypatch.setattr(sf, "CONFIG_ROOT", config.parent / "shipped")
    shutil.copytree(config, config.parent / "shipped" / "sd1", dirs_exist_ok=True)
    _same_weights(load_stable_diffusion(folder), load_stable_diffusion(files / "tiny.safetensors"))


def test_unrecognised_checkpoint_says_what_to_do(tiny, tmp_path):
    folder, files, config = tiny
    with pytest.raises(ModelNotFoundError, match="unrecognised checkpoint") as err:
        load_stable_diffusion(files / "tiny.safetensors")  # tiny widths vs the real SD 1.x config
    assert "--sd-config" in str(err.value) and str(files / "tiny.safetensors") in str(err.value)
    from safetensors.torch import save_file

    junk = tmp_path / "junk.safetensors"
    save_file({"junk": torch.zeros(1)}, str(junk))
    with pytest.raises(ModelNotFoundError, match="not an original-layout") as err:
        load_stable_diffusion(junk)
    assert "diffusers model folder" in str(err.value)
    broken = tmp_path / "broken.ckpt"
    broken.write_bytes(b"not a checkpoint")
    with pytest.raises(ModelNotFoundError, match="cannot read the checkpoint"):
        load_stable_diffusion(broken)
    with pytest.raises(ModelNotFoundError, match="model_index.json"):
        load_stable_diffusion(files / "tiny.safetensors", config=tmp_path)


def test_missing_tokenizer_says_where_to_put_one(tiny, tmp_path, monkeypatch):
    folder, files, config = tiny
    alone = tmp_path / "alone" / "tiny.safetensors"
    alone.parent.mkdir()
    shutil.copy(files / "tiny.safetensors", alone)
    monkeypatch.setattr(sf, "_packaged_bpe", lambda: None)
    with pytest.raises(ModelNotFoundError, match="carry no tokenizer") as err:
        load_stable_diffusion(alone, config=config)
    msg = str(err.value)
    assert str(alone.parent / "tokenizer") in msg and sf.TOKENIZER_ENV in msg
    monkeypatch.setenv(sf.TOKENIZER_ENV, str(files / "tokenizer"))
    assert load_stable_diffusion(alone, config=config).tokenizer.model_max_length == 16


def test_tokenizer_from_a_packaged_clip_bpe_file(tmp_path, monkeypatch):
    """CLIP's vocabulary: 256 byte symbols, the same with '</w>', one token per merge, then start and end."""
    pkg = tmp_path / "site" / "clip"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text("raise ImportError('never imported')\n")
    with gzip.open(pkg / sf.BPE_FILE, "wt") as f:
        f.write("#version: 0.2\nr o\nro s\nros e</w>\n")
    monkeypatch.syspath_prepend(str(tmp_path / "site"))
    tok = sf.find_tokenizer("sd1", tmp_path / "model.safetensors")
    rose, start, end = 512 + 2, 512 + 3, 512 + 4
    assert tok("rose").input_ids == [start, rose, end]
    assert tok.model_max_length == 77 and tok.pad_token == "<|endoftext|>"
    tok2 = sf.find_tokenizer("sd2-base", tmp_path / "model.safetensors")
    assert tok2.pad_token == "!" and tok2.pad_token_id == ord("!") - ord("!")  # '!' is byte symbol 0


def _shapes(**extra):
    base = {"model.diffusion_model.input_blocks.0.0.weight": (320, 4, 3, 3),
            "first_stage_model.encoder.conv_in.weight": (128, 3, 3, 3)}
    return {**base, **extra}


CLIP = {"cond_stage_model.transformer.text_model.embeddings.position_embedding.weight": (77, 768)}
OPEN_CLIP = {"cond_stage_model.model.token_embedding.weight": (49408, 1024)}


def test_family_rule(tmp_path):
    p = tmp_path / "model.safetensors"
    assert sf.detect_family(_shapes(**CLIP), p) == "sd1"
    assert sf.detect_family(_shapes(**OPEN_CLIP), p) == "sd2-base"
    for name in ("v2-1_768-ema-pruned.safetensors", "my-v-pred.ckpt", "model_vpred.safetensors"):
        assert sf.detect_family(_shapes(**OPEN_CLIP), tmp_path / name) == "sd2-768-v", name
    assert sf.detect_family(_shapes(**OPEN_CLIP), tmp_path / "v2-1_512-ema-pruned.safetensors") == "sd2-base"
    assert sf.detect_family(_shapes(**OPEN_CLIP), p, prediction_type="v_prediction") == "sd2-768-v"
    assert sf.detect_family(_shapes(**OPEN_CLIP), tmp_path / "x-768.ckpt", prediction_type="epsilon") == "sd2-base"
    assert sf.detect_family(_shapes(**OPEN_CLIP), p, family="sd2-768-v") == "sd2-768-v"
    (tmp_path / "model.yaml").write_text('model:\n  params:\n    parameterization: "v"\n')
    assert sf.detect_family(_shapes(**OPEN_CLIP), p) == "sd2-768-v"
    with pytest.raises(ModelNotFoundError, match="does not match"):
        sf.detect_family(_shapes(**OPEN_CLIP), p, family="sd1")
    with pytest.raises(ModelNotFoundError, match="SDXL"):
        sf.detect_family(_shapes(**{"conditioner.embedders.1.model.positional_embedding": (77, 1280)}), p)
    with pytest.raises(ModelNotFoundError, match="no text encoder"):
        sf.detect_family(_shapes(), p)
    with pytest.raises(ModelNotFoundError, match="unknown Stable Diffusion family"):
        sf.detect_family(_shapes(**CLIP), p, family="sd3")


# Published sizes (millions of parameters) of the SD parts: UNet 1.x / 2.x, VAE, CLIP ViT-L text, OpenCLIP-H text.
PUBLISHED = {"sd1": (859.52, 83.65, 123.06), "sd2-base": (865.91, 83.65, 340.39), "sd2-768-v": (865.91, 83.65, 340.39)}


@pytest.mark.parametrize("family", list(sf.FAMILIES))
def test_shipped_configs_build_the_published_models(family, tmp_path):
    """Each shipped config builds (on the meta device, no memory) a model of the published size whose original-
    layout names carry the keys diffusers itself reads to tell SD versions apart, and passes the family check."""
    from accelerate import init_empty_weights
    from diffusers import AutoencoderKL, UNet2DConditionModel
    from transformers import CLIPTextConfig, CLIPTextModel

    cfg = sf.config_folder(family)
    with init_empty_weights():
        unet = UNet2DConditionModel.from_config(UNet2DConditionModel.load_config(cfg, subfolder="unet"))
        vae = AutoencoderKL.from_config(AutoencoderKL.load_config(cfg, subfolder="vae"))
        text = CLIPTextModel(CLIPTextConfig.from_pretrained(cfg, subfolder="text_encoder"))
    sizes = tuple(round(sum(p.numel() for p in m.parameters()) / 1e6, 2) for m in (unet, vae, text))
    assert sizes == PUBLISHED[family]
    shapes = {k: tuple(v.shape) for k, v in original_state_dict(unet, vae, text).items()}
    if family != "sd1":  # SD 2.x stores its OpenCLIP text encoder under cond_stage_model.model.*
        shapes = {k.replace("cond_stage_model.transformer.", "cond_stage_model.model."): s for k, s in shapes.items()}
    diffusers_keys = {"sd1": "model.diffusion_model.output_blocks.11.0.skip_connection.weight",
                      "sd2": "model.diffusion_model.input_blocks.2.1.transformer_blocks.0.attn2.to_k.weight"}
    assert diffusers_keys["sd1"] in shapes
    assert shapes[diffusers_keys["sd2"]][-1] == (768 if family == "sd1" else 1024)
    name = tmp_path / ("v2-1_768-ema-pruned.safetensors" if family == "sd2-768-v" else "model.safetensors")
    assert sf.detect_family(shapes, name) == family
    sf.check_matches_config(shapes, cfg, name)
    sched = json.loads((cfg / "scheduler" / "scheduler_config.json").read_text())
    assert sched["prediction_type"] == ("v_prediction" if family == "sd2-768-v" else "epsilon")


def _hf_cache(root, repo: str, folder) -> None:
    base = root / "hub" / f"models--{repo.replace('/', '--')}"
    shutil.copytree(folder, base / "snapshots" / "abc123")
    (base / "refs").mkdir(parents=True)
    (base / "refs" / "main").write_text("abc123")


def test_cached_model_id_resolves_offline(tiny, tmp_path):
    folder, _, _ = tiny
    _hf_cache(tmp_path / "hf-home", "stabilityai/stable-diffusion-2-base", folder)
    path = resolve_model_path("sd", "stabilityai/stable-diffusion-2-base")
    repo = tmp_path / "hf-home" / "hub" / "models--stabilityai--stable-diffusion-2-base"
    assert path == repo / "snapshots" / "abc123"
    _same_weights(load_stable_diffusion(folder), load_stable_diffusion(path))
    with pytest.raises(ModelNotFoundError, match="Hugging Face cache") as err:
        resolve_model_path("sd", "stabilityai/stable-diffusion-2-1")
    assert "--sd-path" in str(err.value)


def test_prediction_type_override_and_unsupported(tiny):
    folder, _, _ = tiny
    assert load_stable_diffusion(folder, prediction_type="v_prediction").prediction_type == "v_prediction"
    with pytest.raises(ModelNotFoundError, match="prediction type"):
        load_stable_diffusion(folder, prediction_type="sample")


@pytest.fixture(scope="module")
def selected_ws(scene_factory, tmp_path_factory):
    """A workspace trained for a few steps on a tiny demo scene, with a selection."""
    from repaint_nerf.app.cli import main

    ws = tmp_path_factory.mktemp("ws") / "ws"
    assert main(["train", str(scene_factory("demo", size=24, views=6)), "--workspace", str(ws), "--steps", "8",
                 "--rays", "256", "--max-samples", "64", "--no-depth"]) == 0
    assert main(["select", str(ws), "--view", "0", "--patch", "6,6,18,18", "--threshold", "0.0", "--no-cleanup",
                 "--out", str(ws.parent / "masks")]) == 0
    return ws


def test_cli_repaint_sd_from_folder_single_file_and_cached_id(selected_ws, tiny, tmp_path, capsys):
    from repaint_nerf.app.cli import main
    from repaint_nerf.core.workspace.workspace import Workspace

    folder, files, config = tiny
    _hf_cache(tmp_path / "hf-home", "stabilityai/stable-diffusion-2-base", folder)
    common = ["--guidance", "sd", "--prompt", "a blue ball", "--steps", "2", "--resolution", "16",
              "--lambda-clip", "0"]
    runs = [["--sd-path", str(folder)], ["--sd-path", str(files / "tiny.safetensors"), "--sd-config", str(config)],
            ["--sd-path", "stabilityai/stable-diffusion-2-base"]]
    for extra in runs:
        before = len(Workspace.open(selected_ws).versions)
        assert main(["repaint", str(selected_ws), *common, *extra]) == 0, capsys.readouterr().err
        assert "saved version" in capsys.readouterr().out
        assert len(Workspace.open(selected_ws).versions) == before + 1
    assert main(["repaint", str(selected_ws), *common, "--sd-path", str(files / "tiny.safetensors")]) == 2
    err = capsys.readouterr().err
    assert "unrecognised checkpoint" in err and "--sd-config" in err
