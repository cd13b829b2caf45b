"""What a single-file Stable Diffusion checkpoint (original CompVis/Stability layout) needs to load offline.

Such a file holds the weights only. The model family is told from its keys and shapes, the family's
small diffusers configuration ships with this package (core/models/configs/<family>/), and the CLIP
tokenizer, which no original checkpoint carries, is found locally (see `find_tokenizer`).

Family rule: text-encoder keys `cond_stage_model.transformer.*` (CLIP ViT-L, cross-attention 768) are
SD 1.x; `cond_stage_model.model.*` (OpenCLIP ViT-H, cross-attention 1024) are SD 2.x. The weights of
SD 2.x base (512 px, epsilon) and 768 (v-prediction) look the same, so in order: an explicit family,
an explicit prediction type (v_prediction -> 768), a `<stem>.yaml` beside the file whose
`parameterization` is "v", the file name (`768`, `v-pred`, `vpred`, `v_pred` -> 768); otherwise 2.x base.
"""
from __future__ import annotations

import gzip
import importlib.util
import json
import os
import re
import tempfile
from dataclasses import dataclass
from pathlib import Path

from repaint_nerf.core.errors import ModelNotFoundError
from repaint_nerf.core.models.paths import cached_snapshot
from repaint_nerf.core.models.sd import PREDICTION_TYPES

CONFIG_ROOT = Path(__file__).parent / "configs"
TOKENIZER_ENV = "REPAINT_NERF_SD_TOKENIZER"
UNET = "model.diffusion_model."
CLIP_TEXT = "cond_stage_model.transformer."
OPEN_CLIP_TEXT = "cond_stage_model.model."
BPE_FILE = "bpe_simple_vocab_16e6.txt.gz"


@dataclass(frozen=True)
class Family:
    """One supported model family: its shipped config folder name, text encoder and tokenizer padding."""

    name: str
    title: str
    text_encoder: str  # 'clip' (ViT-L) or 'open_clip' (ViT-H)
    pad_token: str  # SD 1.x pads prompts with the end token, SD 2.x with '!' (id 0, as OpenCLIP does)
    tokenizer_repos: tuple[tuple[str, str], ...]  # (repo id, subfolder) to look for in the local HF cache


_SD1_REPOS = (("openai/clip-vit-large-patch14", ""), ("stable-diffusion-v1-5/stable-diffusion-v1-5", "tokenizer"),
              ("runwayml/stable-diffusion-v1-5", "tokenizer"), ("CompVis/stable-diffusion-v1-4", "tokenizer"))
_SD2_REPOS = (("stabilityai/stable-diffusion-2-1-base", "tokenizer"),
              ("stabilityai/stable-diffusion-2-base", "tokenizer"),
              ("stabilityai/stable-diffusion-2-1", "tokenizer"), ("stabilityai/stable-diffusion-2", "tokenizer"))
FAMILIES = {
    "sd1": Family("sd1", "SD 1.x (CLIP ViT-L, 512 px, epsilon)", "clip", "<|endoftext|>", _SD1_REPOS + _SD2_REPOS),
    "sd2-base": Family("sd2-base", "SD 2.x base (OpenCLIP ViT-H, 512 px, epsilon)", "open_clip", "!",
                       _SD2_REPOS + _SD1_REPOS),
    "sd2-768-v": Family("sd2-768-v", "SD 2.x 768 (OpenCLIP ViT-H, 768 px, v-prediction)", "open_clip", "!",
                        _SD2_REPOS + _SD1_REPOS),
}
_FAMILY_HINT = f"pass --sd-family ({' | '.join(FAMILIES)}) only for an SD 1.x / 2.x checkpoint"


def config_folder(family: str) -> Path:
    """The shipped diffusers config folder (model_index.json, unet/, vae/, text_encoder/, scheduler/) of a family."""
    return CONFIG_ROOT / FAMILIES[family].name


def checkpoint_shapes(path: Path) -> dict[str, tuple[int, ...]]:
    """Tensor name -> shape of a .safetensors or .ckpt file, without reading the weights (mmap for .ckpt)."""
    try:
        if path.suffix.lower() == ".safetensors":
            from safetensors import safe_open

            with safe_open(str(path), framework="pt") as f:
                return {k: tuple(f.get_slice(k).get_shape()) for k in f.keys()}
        import torch

        sd = torch.load(path, map_location="cpu", mmap=True, weights_only=True)
        while isinstance(sd, dict) and "state_dict" in sd:
            sd = sd["state_dict"]
        return {k: tuple(v.shape) for k, v in sd.items() if hasattr(v, "shape")}
    except Exception as exc:  # safetensors / pickle raise many kinds: all mean "not a readable checkpoint"
        raise ModelNotFoundError(f"cannot read the checkpoint: {exc}", path=path,
                                 hint="check that the file is a complete .safetensors or .ckpt download") from exc


def _says_v_prediction(path: Path) -> bool:
    yaml = path.with_suffix(".yaml")
    if yaml.is_file() and re.search(r"parameterization:\s*['\"]?v['\"]?\s*$", yaml.read_text(errors="ignore"), re.M):
        return True
    return re.search(r"768|v[-_]?pred", path.stem.lower()) is not None


def detect_family(shapes: dict[str, tuple[int, ...]], path: Path, family: str | None = None,
                  prediction_type: str | None = None) -> str:
    """The family of an original-layout checkpoint (see the module docstring for the rule); raises
    ModelNotFoundError saying what to do when the keys are not an SD 1.x / 2.x checkpoint."""
    if family is not None and family not in FAMILIES:
        raise ModelNotFoundError(f"unknown Stable Diffusion family {family!r}", path=path, hint=_FAMILY_HINT)
    if prediction_type is not None and prediction_type not in PREDICTION_TYPES:
        raise ModelNotFoundError(f"unknown prediction type {prediction_type!r}", path=path,
                                 hint=f"use one of: {', '.join(PREDICTION_TYPES)}")
    if any(k.startswith("conditioner.embedders.") for k in shapes):
        raise ModelNotFoundError("this looks like an SDXL checkpoint, which is not supported", path=path,
                                 hint="use an SD 1.x or 2.x model (e.g. SD 1.5 or 2.1-base)")
    if not any(k.startswith(UNET) for k in shapes):
        raise ModelNotFoundError("not an original-layout Stable Diffusion checkpoint (no model.diffusion_model.* "
                                 "weights)", path=path,
                                 hint="give a full SD 1.x/2.x .safetensors/.ckpt, or a diffusers model folder")
    if any(k.startswith(CLIP_TEXT) for k in shapes):
        text = "clip"
    elif any(k.startswith(OPEN_CLIP_TEXT) for k in shapes):
        text = "open_clip"
    else:
        raise ModelNotFoundError("the checkpoint has no text encoder (cond_stage_model.*)", path=path,
                                 hint="use a full SD checkpoint (UNet, VAE and text encoder), or a diffusers folder")
    if family is not None:
        if FAMILIES[family].text_encoder != text:
            raise ModelNotFoundError(f"--sd-family {family} does not match the checkpoint's "
                                     f"{'CLIP ViT-L (SD 1.x)' if text == 'clip' else 'OpenCLIP (SD 2.x)'} text encoder",
                                     path=path, hint="leave --sd-family out to detect it")
        return family
    if text == "clip":
        return "sd1"
    if prediction_type is not None:
        return "sd2-768-v" if prediction_type == "v_prediction" else "sd2-base"
    return "sd2-768-v" if _says_v_prediction(path) else "sd2-base"


def check_matches_config(shapes: dict[str, tuple[int, ...]], config: Path, path: Path) -> None:
    """Fail clearly when the checkpoint's UNet input channels or cross-attention width differ from `config`."""
    unet = json.loads((config / "unet" / "config.json").read_text())
    conv_in = shapes.get(UNET + "input_blocks.0.0.weight")
    if conv_in is not None and conv_in[1] != unet["in_channels"]:
        raise ModelNotFoundError(f"the UNet takes {conv_in[1]} input channels, not {unet['in_channels']} "
                                 f"(inpainting and depth checkpoints are not supported)", path=path,
                                 hint="use a text-to-image SD 1.x/2.x checkpoint")
    to_k = [s for k, s in shapes.items() if k.startswith(UNET) and k.endswith("attn2.to_k.weight")]
    if to_k and to_k[0][-1] != unet["cross_attention_dim"]:
        raise ModelNotFoundError(
            f"unrecognised checkpoint: cross-attention width {to_k[0][-1]}, the config {config} expects "
            f"{unet['cross_attention_dim']}", path=path,
            hint="pass --sd-config DIR with the diffusers config folder of this model (model_index.json, unet/, "
                 "vae/, text_encoder/, scheduler/), or convert it to a diffusers folder")


def is_tokenizer_folder(folder: Path) -> bool:
    """A saved CLIP tokenizer: tokenizer.json, or vocab.json with merges.txt."""
    return (folder / "tokenizer.json").is_file() or ((folder / "vocab.json").is_file()
                                                     and (folder / "merges.txt").is_file())


def _hub_tokenizer(repo: str, subfolder: str) -> Path | None:
    snap = cached_snapshot(repo)
    folder = snap / subfolder if snap is not None and subfolder else snap
    return folder if folder is not None and is_tokenizer_folder(folder) else None


def _packaged_bpe() -> Path | None:
    """The CLIP BPE merges file of an installed `clip` / `open_clip` package (found without importing it)."""
    for name in ("open_clip", "clip"):
        try:
            spec = importlib.util.find_spec(name)
        except (ImportError, ValueError):
            continue
        for loc in (spec.submodule_search_locations or []) if spec else []:
            if (Path(loc) / BPE_FILE).is_file():
                return Path(loc) / BPE_FILE
    return None


def _bytes_to_unicode() -> dict[int, str]:
    """CLIP's (and GPT-2's) byte -> printable character table, in its order: printable bytes map to themselves,
    the rest to code points from 256 up."""
    keep = [*range(ord("!"), ord("~") + 1), *range(ord("\u00a1"), ord("\u00ac") + 1),
            *range(ord("\u00ae"), ord("\u00ff") + 1)]
    chars, extra = list(keep), 0
    for b in range(256):
        if b not in keep:
            keep.append(b)
            chars.append(256 + extra)
            extra += 1
    return {b: chr(c) for b, c in zip(keep, chars)}


def tokenizer_files_from_bpe(bpe: Path, out: Path) -> Path:
    """vocab.json + merges.txt in `out` from CLIP's gzipped BPE merges, built as CLIP's own tokenizer does:
    256 byte symbols, the same with '</w>', one token per merge, then the start and end tokens."""
    lines = gzip.open(bpe, "rt", encoding="utf-8").read().split("\n")
    merges = [tuple(m.split()) for m in lines[1:49152 - 256 - 2 + 1] if m.strip()]
    symbols = list(_bytes_to_unicode().values())
    vocab = symbols + [s + "</w>" for s in symbols] + ["".join(m) for m in merges]
    vocab += ["<|startoftext|>", "<|endoftext|>"]
    out.mkdir(parents=True, exist_ok=True)
    (out / "vocab.json").write_text(json.dumps({t: i for i, t in enumerate(vocab)}, ensure_ascii=False))
    (out / "merges.txt").write_text("#version: 0.2\n" + "\n".join(" ".join(m) for m in merges) + "\n",
                                    encoding="utf-8")
    return out


def tokenizer_sources(family: str, checkpoint: Path, config: Path | None) -> list[tuple[str, Path]]:
    """Where a tokenizer is looked for, in order: (description, folder) for those that exist."""
    cands = []
    if config is not None:
        cands.append(("the config folder's tokenizer/", config / "tokenizer"))
    cands.append(("tokenizer/ beside the checkpoint", checkpoint.parent / "tokenizer"))
    if os.environ.get(TOKENIZER_ENV):
        cands.append((f"${TOKENIZER_ENV}", Path(os.environ[TOKENIZER_ENV]).expanduser()))
    out = [(d, p) for d, p in cands if is_tokenizer_folder(p)]
    for repo, sub in FAMILIES[family].tokenizer_repos:
        folder = _hub_tokenizer(repo, sub)
        if folder is not None:
            out.append((f"{repo} in the local Hugging Face cache", folder))
    return out


def find_tokenizer(family: str, checkpoint: Path, config: Path | None = None):
    """A CLIPTokenizer for a single-file checkpoint, from local files only (see `tokenizer_sources`), else
    built from the CLIP BPE file an installed clip/open_clip package ships; else a message saying what to do."""
    from transformers import CLIPTokenizer

    fam = FAMILIES[family]
    sources = tokenizer_sources(family, checkpoint, config)
    if sources:
        tok = CLIPTokenizer.from_pretrained(str(sources[0][1]), local_files_only=True)
    else:
        bpe = _packaged_bpe()
        if bpe is None:
            raise ModelNotFoundError(
                "original Stable Diffusion checkpoints carry no tokenizer, and none was found locally",
                path=checkpoint,
                hint=f"copy a CLIP tokenizer folder (tokenizer.json, or vocab.json and merges.txt: e.g. the "
                     f"tokenizer/ folder of any diffusers SD 1.x/2.x model) to {checkpoint.parent / 'tokenizer'}, "
                     f"or set {TOKENIZER_ENV}=DIR, or have openai/clip-vit-large-patch14 in the Hugging Face cache")
        with tempfile.TemporaryDirectory() as tmp:  # the tokenizer reads both files when built
            folder = tokenizer_files_from_bpe(bpe, Path(tmp))
            tok = CLIPTokenizer(str(folder / "vocab.json"), str(folder / "merges.txt"), model_max_length=77)
    if fam.pad_token in tok.get_vocab() and tok.pad_token != fam.pad_token:
        tok.pad_token = fam.pad_token
    return tok
