"""The sampling pass of the ray marcher as a native CPU kernel (core/render/csrc/march.c), called through ctypes.

The PyTorch path (raymarch.next_segments + expand_segments) tests coarse segments, expands them into
steps and tests each step: about twenty tensor operations per round, a third of a 128x128 render on a
2-core CPU. The kernel walks each ray once, crossing empty cells in one jump, and emits the same samples.
It serves bounded fields and warped ones (contraction, NDC; cone steps) on the CPU; CUDA tensors take the PyTorch
path.
"""
from __future__ import annotations

import ctypes
from pathlib import Path

import torch
from torch import Tensor

from repaint_nerf.core.field.contraction import ContractWarp, NDCWarp
from repaint_nerf.core.native import NativeLibrary
from repaint_nerf.core.render.occupancy import OccupancyGrid
from repaint_nerf.core.render.raymarch import RayPlan, Samples


def _bind(lib: ctypes.CDLL) -> ctypes.CDLL:
    p, i64, i32, u64, f32 = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int32, ctypes.c_uint64, ctypes.c_float
    lib.mr_march.argtypes = [p, p, p, p, p, f32, f32, p, i64, p, i32, p, p, i32, i32, i32, f32, i32, p, i32, u64,
                             p, p, p, p, p, p, i32]
    lib.mr_march.restype = i64
    return lib


MAX_CASCADES = 16  # march.c's limit
BLOCK = 4  # cells per axis of the coarse level that crosses large empty regions in one jump
LIBRARY = NativeLibrary(Path(__file__).with_name("csrc") / "march.c", _bind, "ray-marching")


_NO_WARP_PARAMS = torch.zeros(15)  # march.c reads its warp parameters for NDC only
_WARP_KINDS = ((ContractWarp, 1), (NDCWarp, 2))  # march.c's warp kinds (0: none)


def _warp_kind(warp) -> int | None:
    """march.c's kind for a grid's warp; None for a warp the kernel does not know."""
    if warp is None:
        return 0
    return next((kind for cls, kind in _WARP_KINDS if isinstance(warp, cls)), None)


def _warp_params(warp) -> Tensor:
    """The 15 floats march.c reads for NDC: world-to-camera rotation (row-major) and translation, ax, ay, near."""
    if not isinstance(warp, NDCWarp):
        return _NO_WARP_PARAMS
    w2c = warp.w2c.float()
    return torch.cat([w2c[:3, :3].reshape(-1), w2c[:3, 3], torch.tensor([warp.ax, warp.ay, warp.near])])


def usable(origins: Tensor, plan: RayPlan, grid: OccupancyGrid | None) -> bool:
    """Whether the kernel can march these rays: CPU float32, a grid it knows the warp of, a built library."""
    return (grid is not None and _warp_kind(grid.warp) is not None and grid.cascades <= MAX_CASCADES
            and origins.device.type == "cpu"
            and grid.device.type == "cpu" and origins.dtype == torch.float32 and LIBRARY.get() is not None)


def march(origins: Tensor, dirs: Tensor, plan: RayPlan, grid: OccupancyGrid, ids: Tensor, next_k: Tensor,
          take: int, perturb: bool) -> Samples:
    """For rays `ids` (sorted), their next `take` occupied samples from step `next_k` on (advanced in place);
    packed, sorted by ray then distance. Jitter (perturb) draws its seed from PyTorch's generator."""
    n_ids = int(ids.numel())
    if n_ids == 0:
        take = 1
    else:  # no ray can emit more than its remaining steps: the buffers need no more room
        take = max(1, min(int(take), int((plan.n_steps[ids] - next_k[ids]).max())))
    cap = n_ids * take
    ray = torch.empty(cap, dtype=torch.long)
    ts, te, t = torch.empty(cap), torch.empty(cap), torch.empty(cap)
    x = torch.empty(cap, 3)
    count = torch.empty(n_ids, dtype=torch.int32)
    seed = int(torch.randint(0, 2 ** 62, (1,)).item()) if perturb else 0
    tensors = [origins.contiguous(), dirs.contiguous(), plan.t_near.contiguous(), plan.t_far.contiguous(),
               plan.n_steps.contiguous(), ids.contiguous(), grid.occupied.contiguous()]
    o, d, tn, tf, n, idc, occ = tensors
    factor = BLOCK if grid.resolution % BLOCK == 0 and grid.resolution > BLOCK else 1
    coarse = grid.blocks(factor).contiguous() if factor > 1 else occ
    assert next_k.is_contiguous() and next_k.dtype == torch.long
    kind, params = _warp_kind(grid.warp), _warp_params(grid.warp)
    total = LIBRARY.get().mr_march(
        o.data_ptr(), d.data_ptr(), tn.data_ptr(), tf.data_ptr(), n.data_ptr(), float(plan.step),
        float(max(plan.cone, 0.0)), idc.data_ptr(), n_ids, next_k.data_ptr(), take, occ.data_ptr(), coarse.data_ptr(),
        factor, grid.resolution, grid.cascades, float(grid.bound), kind, params.data_ptr(), int(bool(perturb)), seed,
        ray.data_ptr(), ts.data_ptr(), te.data_ptr(), t.data_ptr(), x.data_ptr(), count.data_ptr(),
        torch.get_num_threads())
    if total < 0:
        raise ValueError(f"the native marcher supports 1 to 16 cascades, and one with a warp (got {grid.cascades})")
    return Samples(ray[:total], ts[:total], te[:total], t[:total], x[:total])
