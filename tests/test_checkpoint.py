"""Checkpoints: round trip of tensors, optimiser state and header; clear errors for bad files;
a trained field saved and loaded renders identically."""
from __future__ import annotations

import json

import pytest
import torch

from repaint_nerf.core.errors import WorkspaceError
from repaint_nerf.core.train.checkpoint import (CHECKPOINT_FORMAT, HEADER_KEY, Checkpoint, load_optimizer_state,
                                   optimizer_state)


def test_round_trip(tmp_path):
    ck = Checkpoint({"field.a": torch.randn(5, 3), "grid.b": torch.arange(7, dtype=torch.uint8)},
                    {"kind": "stage1", "step": 12, "cfg": {"x": [1, 2]}})
    ck.save(tmp_path / "c.safetensors")
    back = Checkpoint.load(tmp_path / "c.safetensors")
    assert back.header["format"] == CHECKPOINT_FORMAT and back.header["step"] == 12
    assert back.header["cfg"] == {"x": [1, 2]}
    for k, v in ck.tensors.items():
        assert torch.equal(back.tensors[k], v) and back.tensors[k].dtype == v.dtype
    assert set(back.section("field")) == {"a"}


def test_optimizer_state_round_trip():
    torch.manual_seed(0)
    model = torch.nn.Linear(4, 2)
    opt = torch.optim.Adam(model.parameters(), lr=1e-2, betas=(0.9, 0.99), eps=1e-15)
    for _ in range(3):
        opt.zero_grad()
        model(torch.randn(8, 4)).pow(2).sum().backward()
        opt.step()
    tensors, meta = optimizer_state(opt)
    tensors = {k: v.clone() for k, v in tensors.items()}  # as if read back from a file
    meta = json.loads(json.dumps(meta))
    model2 = torch.nn.Linear(4, 2)
    model2.load_state_dict(model.state_dict())
    opt2 = torch.optim.Adam(model2.parameters(), lr=1.0)
    load_optimizer_state(opt2, tensors, meta)
    x = torch.randn(8, 4)
    for m, o in ((model, opt), (model2, opt2)):
        o.zero_grad()
        m(x).pow(2).sum().backward()
        o.step()
    assert opt2.param_groups[0]["lr"] == 1e-2
    for p, q in zip(model.parameters(), model2.parameters()):
        assert torch.equal(p, q)


def test_mismatched_version(tmp_path):
    from safetensors.torch import save_file

    path = tmp_path / "old.safetensors"
    save_file({"x": torch.zeros(2)}, str(path), metadata={HEADER_KEY: json.dumps({"format": CHECKPOINT_FORMAT + 1})})
    with pytest.raises(WorkspaceError, match="format version") as exc:
        Checkpoint.load(path)
    assert str(path) in str(exc.value)


def test_no_header(tmp_path):
    from safetensors.torch import save_file

    path = tmp_path / "foreign.safetensors"
    save_file({"x": torch.zeros(2)}, str(path))
    with pytest.raises(WorkspaceError, match="no repaint-nerf header"):
        Checkpoint.load(path)


@pytest.mark.parametrize("keep", [0.5, 0.99, 0.0])
def test_truncated(tmp_path, keep):
    path = tmp_path / "c.safetensors"
    Checkpoint({"field.a": torch.randn(1000)}, {"kind": "stage1"}).save(path)
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])
    with pytest.raises(WorkspaceError, match="cannot read this checkpoint"):
        Checkpoint.load(path)


def test_missing(tmp_path):
    with pytest.raises(WorkspaceError, match="not found"):
        Checkpoint.load(tmp_path / "none.safetensors")
