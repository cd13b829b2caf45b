"""Tiny random-weight ONNX teachers, exported from torch, for the feature and depth teacher tests."""
from __future__ import annotations

from pathlib import Path

import torch


def export_feature_net(path: Path, dim: int = 6, seed: int = 0) -> tuple[torch.nn.Module, Path]:
    """A 2-layer conv net image (1, 3, H, W) -> features (1, dim, H/2, W/2), any input size; (net, path)."""
    torch.manual_seed(seed)
    net = torch.nn.Sequential(torch.nn.Conv2d(3, 8, 3, stride=2, padding=1), torch.nn.ReLU(),
                              torch.nn.Conv2d(8, dim, 3, padding=1)).eval()
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.onnx.export(net, (torch.zeros(1, 3, 32, 32),), str(path), dynamo=False, input_names=["image"],
                      output_names=["features"],
                      dynamic_axes={"image": {2: "h", 3: "w"}, "features": {2: "fh", 3: "fw"}})
    return net, path


def export_depth_net(path: Path) -> Path:
    """A fixed 1x1 conv "depth model": relative inverse depth = 0.2 + mean of the input channels."""
    net = torch.nn.Conv2d(3, 1, 1)
    with torch.no_grad():
        net.weight.fill_(1.0 / 3.0)
        net.bias.fill_(0.2)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.onnx.export(net.eval(), (torch.zeros(1, 3, 16, 16),), str(path), dynamo=False,
                      input_names=["x"], output_names=["depth"],
                      dynamic_axes={"x": {2: "h", 3: "w"}, "depth": {2: "h", 3: "w"}})
    return path
