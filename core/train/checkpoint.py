"""Checkpoint files: tensors in safetensors plus a JSON header (format version, configs, step).

Holds the field, the occupancy grid, the optimiser state and the RNG state, so a resumed run continues
where it stopped. Loading reads safetensors only (no pickle); a corrupt, truncated or other-version
file is a WorkspaceError that names the file.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from repaint_nerf.core.errors import WorkspaceDamaged, WorkspaceError
from repaint_nerf.core.train.header import DAMAGED_HINT, FORMAT_VERSION, HEADER_KEY, CheckpointHeader, check_format
from repaint_nerf.core.workspace import atomic
from repaint_nerf.core.workspace.integrity import STAMP_KEY, IntegrityError, verify_file, workspace_of

CHECKPOINT_FORMAT = FORMAT_VERSION  # the version written; older ones are read (core.train.header)


@dataclass
class Checkpoint:
    """Flat tensors (names like 'field.x', 'grid.x', 'optim.3.exp_avg') and a JSON-able header (the raw
    container: `info` reads it through the schema, `core.train.header.CheckpointHeader`)."""

    tensors: dict[str, torch.Tensor] = field(default_factory=dict)
    header: dict[str, Any] = field(default_factory=dict)

    @staticmethod
    def of(tensors: dict[str, torch.Tensor], header: CheckpointHeader) -> "Checkpoint":
        """A checkpoint with a schema header (what the trainers write)."""
        return Checkpoint(tensors, header.to_dict())

    @property
    def info(self) -> CheckpointHeader:
        """The header read through the schema (older formats upgraded)."""
        return CheckpointHeader.from_dict(self.header)

    def save(self, path: str | Path, stamp: dict | None = None) -> str:
        """Write atomically to `path` (the previous file stays intact if anything fails), sealed with its content
        hash (returned); `stamp` is a workspace version's identity (core.workspace.workspace.save_version)."""
        header = {"format": CHECKPOINT_FORMAT, **self.header}
        meta = {HEADER_KEY: json.dumps(header)}
        if stamp is not None:
            meta[STAMP_KEY] = json.dumps(stamp)
        return atomic.write_safetensors(path, self.tensors, meta)

    @staticmethod
    def load(path: str | Path, device: torch.device | str = "cpu") -> "Checkpoint":
        """Read a checkpoint; raises WorkspaceError for a missing, corrupt or unreadable-version file."""
        path = Path(path)
        tensors: dict[str, torch.Tensor] = {}
        header = _read(path, tensors, device)
        return Checkpoint(tensors, header)

    def section(self, prefix: str) -> dict[str, torch.Tensor]:
        """The tensors under 'prefix.' with the prefix removed."""
        p = prefix + "."
        return {k[len(p):]: v for k, v in self.tensors.items() if k.startswith(p)}


def read_header(path: str | Path) -> CheckpointHeader:
    """The header of a checkpoint or version file, without reading its tensors."""
    path = Path(path)
    return CheckpointHeader.from_dict(_read(path, None), path)


def _read(path: Path, tensors: dict | None, device: torch.device | str = "cpu") -> dict:
    """The raw header of a checkpoint file (format checked), filling `tensors` unless it is None. Reading the
    tensors first checks the file's content hash: damaged data is refused, never used."""
    from safetensors import safe_open

    if not path.is_file():
        raise WorkspaceError("checkpoint not found", path, hint="train first (repaint-nerf train)")
    if tensors is not None:
        try:
            verify_file(path)
        except (IntegrityError, OSError) as exc:
            raise _damaged(path, f"cannot read this checkpoint: {exc}") from exc
    try:
        with safe_open(str(path), framework="pt", device=str(device)) as f:
            meta = f.metadata() or {}
            for k in f.keys() if tensors is not None else ():
                tensors[k] = f.get_tensor(k)
    except Exception as exc:  # safetensors raises its own error types for truncated/garbled files
        raise _damaged(path, f"cannot read this checkpoint ({exc.__class__.__name__}: {exc})") from exc
    try:
        header = json.loads(meta[HEADER_KEY])
    except (KeyError, json.JSONDecodeError) as exc:
        raise WorkspaceError("this safetensors file has no repaint-nerf header", path, hint=DAMAGED_HINT) from exc
    check_format(header.get("format") if isinstance(header, dict) else None, path)
    return header


def _damaged(path: Path, problem: str) -> WorkspaceError:
    """The error for a damaged checkpoint: inside a workspace it offers `repair`, elsewhere DAMAGED_HINT."""
    ws = workspace_of(path)
    if ws is None:
        return WorkspaceError(problem, path, hint=DAMAGED_HINT)
    return WorkspaceDamaged(problem, path, workspace=ws)


def split_state(state: dict) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """Split a state_dict into its tensors and its JSON-able rest (ints, floats, lists)."""
    tensors = {k: v for k, v in state.items() if isinstance(v, torch.Tensor)}
    rest = {k: v for k, v in state.items() if not isinstance(v, torch.Tensor)}
    json.dumps(rest)  # fail here, not on load, if a component keeps non-JSON state
    return tensors, rest


def optimizer_state(opt: torch.optim.Optimizer) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """Adam-style optimiser state as flat tensors 'i.key' plus JSON param groups."""
    sd = opt.state_dict()
    tensors = {}
    scalars: dict[str, dict] = {}
    for pid, st in sd["state"].items():
        for key, val in st.items():
            if isinstance(val, torch.Tensor):
                tensors[f"{pid}.{key}"] = val
            else:
                scalars.setdefault(str(pid), {})[key] = val
    return tensors, {"param_groups": sd["param_groups"], "scalars": scalars}


def load_optimizer_state(opt: torch.optim.Optimizer, tensors: dict[str, torch.Tensor], meta: dict) -> None:
    """Inverse of `optimizer_state` (tensors moved to the parameters' device)."""
    state: dict[int, dict] = {}
    for name, val in tensors.items():
        pid, key = name.split(".", 1)
        state.setdefault(int(pid), {})[key] = val
    for pid, d in meta.get("scalars", {}).items():
        state.setdefault(int(pid), {}).update(d)
    opt.load_state_dict({"state": state, "param_groups": meta["param_groups"]})
