"""Token merging on the UNet's self-attention (core.models.sd_tome): the bipartite merge against a plain
loop reference, off means the exact UNet, on means fewer tokens and a guidance gradient close to the unmerged
one on the tiny pipeline, and the option reaches the guidance from RepaintConfig."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from repaint_nerf.core.errors import UserError
from repaint_nerf.core.models.sd import load_stable_diffusion
from repaint_nerf.core.models.sd_tome import TokenMergingProcessor, bipartite_merge, set_token_merging
from repaint_nerf.core.repaint.sds import SDSGuidance
from tiny_diffusion import cached

# Cosine of the SDS image gradient with half the highest-resolution tokens merged vs none, tiny pipeline
# (8x8 latents, guidance scale 100): measured 0.990-0.995 over seeds 0-7, norm ratio 0.97-1.08.
TOME_COSINE_BAR = 0.98


def reference_merge_unmerge(x: np.ndarray, h: int, w: int, r: int) -> tuple[np.ndarray, int]:
    """Plain loops: sources (all but each 2x2 cell's top-left) ranked by their best cosine to a destination;
    the top r are averaged into it; every merged source then reads its destination's average."""
    b, n, _ = x.shape
    dst = [y * w + xx for y in range(h) for xx in range(w) if y % 2 == 0 and xx % 2 == 0]
    src = [i for i in range(n) if i not in dst]
    out = x.copy()
    for k in range(b):
        unit = x[k] / np.linalg.norm(x[k], axis=1, keepdims=True)
        best = {s: max(dst, key=lambda d: unit[s] @ unit[d]) for s in src}
        score = {s: unit[s] @ unit[best[s]] for s in src}
        merged = sorted(src, key=lambda s: -score[s])[:r]
        for d in dst:
            group = [d] + [s for s in merged if best[s] == d]
            out[k, group] = x[k, group].mean(axis=0)
    return out, n - r


def test_bipartite_merge_matches_the_loop_reference():
    gen = torch.Generator().manual_seed(0)
    x = torch.randn(2, 36, 5, generator=gen, dtype=torch.float64)
    for r in (0, 7, 27):
        merge, unmerge = bipartite_merge(x, 6, 6, r)
        merged = merge(x)
        want, n_left = reference_merge_unmerge(x.numpy(), 6, 6, r)
        assert merged.shape == (2, n_left, 5)
        np.testing.assert_allclose(unmerge(merged).numpy(), want, atol=1e-12)


@pytest.fixture()
def sd(tmp_path_factory):
    return load_stable_diffusion(cached("sd", tmp_path_factory))


def _image_grad(sd, seed: int) -> torch.Tensor:
    img = torch.rand(1, 3, 64, 64, generator=torch.Generator().manual_seed(100 + seed)).requires_grad_(True)
    SDSGuidance(sd, "a blue rose", seed=seed).loss(img, None, 0, 0)["loss"].backward()
    return img.grad.detach().double().flatten()


def test_off_is_the_exact_unet_and_on_merges_tokens(sd, monkeypatch):
    lat = torch.randn(2, 4, 8, 8, generator=torch.Generator().manual_seed(3))
    t = torch.tensor([500, 500])
    emb = sd.encode_text(["", "a rose"])
    plain = sd.predict_noise(lat, t, emb)
    assert set_token_merging(sd.unet, 0.5, min_tokens=0) == 3  # the first down block (1 layer) and the last up block (2)
    seen = []
    real = TokenMergingProcessor.__call__

    def spy(self, attn, hidden_states, *a, **k):
        seen.append(hidden_states.shape[1])
        inner = self.inner

        def inner_spy(attn_, hs, *a_, **k_):
            seen.append(hs.shape[1])
            return inner(attn_, hs, *a_, **k_)

        self.inner = inner_spy
        try:
            return real(self, attn, hidden_states, *a, **k)
        finally:
            self.inner = inner

    monkeypatch.setattr(TokenMergingProcessor, "__call__", spy)
    merged = sd.predict_noise(lat, t, emb)
    assert seen and seen[0::2] == [64] * (len(seen) // 2) and seen[1::2] == [32] * (len(seen) // 2)
    assert not torch.equal(merged, plain)
    assert set_token_merging(sd.unet, 0.0) == 0
    assert torch.equal(sd.predict_noise(lat, t, emb), plain)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_merged_guidance_gradient_close_to_unmerged(sd, seed):
    ref = _image_grad(sd, seed)
    set_token_merging(sd.unet, 0.5, min_tokens=0)
    got = _image_grad(sd, seed)
    cos = float(torch.nn.functional.cosine_similarity(ref, got, dim=0))
    assert torch.isfinite(got).all() and cos > TOME_COSINE_BAR, cos
    assert not torch.equal(ref, got)


def test_small_grids_are_not_merged(sd):
    lat = torch.randn(2, 4, 8, 8, generator=torch.Generator().manual_seed(4))
    t, emb = torch.tensor([300, 300]), sd.encode_text(["", "a rose"])
    plain = sd.predict_noise(lat, t, emb)
    set_token_merging(sd.unet, 0.5)  # the tiny UNet's 64 tokens are below MIN_TOKENS
    assert torch.equal(sd.predict_noise(lat, t, emb), plain)
    set_token_merging(sd.unet, 0.5, min_tokens=64)
    assert not torch.equal(sd.predict_noise(lat, t, emb), plain)


def test_ratio_out_of_range(sd):
    for bad in (-0.1, 0.8):
        with pytest.raises(UserError, match="token-merging ratio"):
            set_token_merging(sd.unet, bad)


def test_the_config_and_flag_reach_the_unet(sd):
    import argparse
    from types import SimpleNamespace

    from repaint_nerf.app.commands.repaint import add_arguments, config_from_args
    from repaint_nerf.core.repaint.config import RepaintConfig
    from repaint_nerf.core.repaint.registry import GuidanceInputs, get

    p = argparse.ArgumentParser()
    add_arguments(p)
    cfg = config_from_args(p.parse_args(["ws", "--token-merging", "0.25"]))
    assert cfg.sd_token_merging == 0.25
    assert config_from_args(p.parse_args(["ws"])).sd_token_merging == RepaintConfig().sd_token_merging
    t = SimpleNamespace(prompt="a rose", cfg=cfg, device=torch.device("cpu"), workspace=None)
    guidance = get("sd").factory(t, GuidanceInputs(sd_path=sd.path))  # what the trainer builds
    procs = [m.processor for n, m in guidance.sd.unet.named_modules() if n.endswith("attn1")]
    merged = [p for p in procs if isinstance(p, TokenMergingProcessor)]
    assert len(merged) == 3 and all(p.ratio == 0.25 for p in merged)


def test_merging_wraps_the_sliced_attention_that_cuda_uses(sd):
    """On CUDA the UNet runs diffusers' SlicedAttnProcessor, whose call takes no `temb`: merging over it runs and
    still merges (it raised TypeError on the first CUDA run)."""
    from diffusers.models.attention_processor import SlicedAttnProcessor

    sd.unet.set_attn_processor(SlicedAttnProcessor(slice_size=1))
    lat = torch.randn(2, 4, 8, 8, generator=torch.Generator().manual_seed(5))
    t, emb = torch.tensor([400, 400]), sd.encode_text(["", "a rose"])
    plain = sd.predict_noise(lat, t, emb)
    assert set_token_merging(sd.unet, 0.5, min_tokens=0) == 3
    merged = sd.predict_noise(lat, t, emb)
    assert merged.shape == plain.shape and torch.isfinite(merged).all() and not torch.equal(merged, plain)
