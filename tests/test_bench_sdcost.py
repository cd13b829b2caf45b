"""bench sdcost on the tiny pipeline (the real architectures are too big for a test): options take turns over
rounds with the fp32 ones first, each UNet-changing option reports its gradient cosine with fp32, bad input."""
from __future__ import annotations

import pytest
import torch

from repaint_nerf.core.bench import sdcost
from repaint_nerf.core.errors import UserError
from repaint_nerf.core.models.sd import load_stable_diffusion
from test_sd_speed import make_tiny_autoencoder
from tiny_diffusion import cached


def test_rounds_take_turns_fp32_first_and_cosines(tmp_path, tmp_path_factory, monkeypatch):
    folder = cached("sd", tmp_path_factory)
    monkeypatch.setattr(sdcost, "build_sd", lambda family, device, dtype: load_stable_diffusion(folder, device))
    from diffusers import AutoencoderTiny

    ae = AutoencoderTiny.from_pretrained(make_tiny_autoencoder(tmp_path / "ae")).eval().requires_grad_(False)
    monkeypatch.setattr(sdcost, "build_tiny_autoencoder", lambda device: ae)
    said, snapshots = [], []
    names = ["bf16+tiny_ae+nhwc+tome", "baseline", "bf16_unet"]
    r = sdcost.measure("cpu", steps=1, size=16, options=names, rounds=2, progress=said.append,
                       on_option=lambda res: snapshots.append(len(res["options"])))
    started = [m.split(":")[1].split(" (")[0].strip() for m in said if m.endswith("...")]
    # fp32 first (bf16 is one-way), then the bf16 options alternating round by round
    assert started == ["baseline", "baseline", "bf16+tiny_ae+nhwc+tome", "bf16_unet", "bf16+tiny_ae+nhwc+tome",
                       "bf16_unet"]
    assert r["rounds"] == 2 and r["timed_steps_per_option"] == 2 and len(snapshots) == 6
    for name in names:
        opt = r["options"][name]
        assert len(opt["step_seconds_all"]) == 2 and opt["step_seconds"] > 0 and opt["step_cpu_seconds"] > 0
    assert "grad_cosine" not in r["options"]["baseline"]
    tome, bf16 = r["options"]["bf16+tiny_ae+nhwc+tome"]["grad_cosine"], r["options"]["bf16_unet"]["grad_cosine"]
    assert set(tome) == set(bf16) == {str(t) for t in sdcost.COSINE_TIMESTEPS}
    assert all(0.9 < c < 1.0 for c in [*tome.values(), *bf16.values()])
    assert r["bf16_grad_cosine"] == bf16 and r["speedup_vs_baseline"]["baseline"] == 1.0


def test_bad_requests():
    for kw in (dict(options=["nope"]), dict(steps=0), dict(rounds=0)):
        with pytest.raises(UserError, match="bad sdcost request"):
            sdcost.measure("cpu", **kw)
