"""Adan against a plain reference loop of the algorithm (Xie et al. 2022), plus the project's step rules."""
from __future__ import annotations

import math

import pytest
import torch

from repaint_nerf.core.train.adan import OFFICIAL_LR, OFFICIAL_MULTIPLIERS, Adan, grads_finite, param_groups


def reference_adan(params0, grad_fn, lrs, steps, betas=(0.98, 0.92, 0.99), eps=1e-8, wd=0.0,
                   max_norm=0.0, no_prox=True):
    """Adan written out from the paper's update rules, one tensor at a time (no optimiser class)."""
    b1, b2, b3 = betas
    ps = [p.clone() for p in params0]
    m = [torch.zeros_like(p) for p in ps]
    v = [torch.zeros_like(p) for p in ps]
    n = [torch.zeros_like(p) for p in ps]
    prev = None
    for k in range(1, steps + 1):
        gs = grad_fn(ps)
        if max_norm > 0:
            total = math.sqrt(sum(float(g.pow(2).sum()) for g in gs)) + eps
            gs = [g * min(1.0, max_norm / total) for g in gs]
        prev = gs if prev is None else prev  # first step: no gradient difference
        bc1, bc2, bc3 = 1 - b1 ** k, 1 - b2 ** k, 1 - b3 ** k
        for i, (g, lr) in enumerate(zip(gs, lrs)):
            diff = g - prev[i]
            m[i] = b1 * m[i] + (1 - b1) * g
            v[i] = b2 * v[i] + (1 - b2) * diff
            n[i] = b3 * n[i] + (1 - b3) * (g + b2 * diff) ** 2
            update = (m[i] / bc1 + b2 * v[i] / bc2) / (n[i].sqrt() / math.sqrt(bc3) + eps)
            if no_prox:
                ps[i] = ps[i] * (1 - lr * wd) - lr * update
            else:
                ps[i] = (ps[i] - lr * update) / (1 + lr * wd)
        prev = gs
    return ps


def _problem():
    torch.manual_seed(0)
    x = torch.randn(16, 3, dtype=torch.float64)
    y = torch.sin(x.sum(1, keepdim=True))
    w0 = torch.randn(3, 1, dtype=torch.float64)
    b0 = torch.randn(1, dtype=torch.float64)

    def loss(w, b):
        return ((torch.tanh(x @ w + b) - y) ** 2).mean()

    def grad_fn(ps):
        w, b = (p.detach().requires_grad_(True) for p in ps)
        return list(torch.autograd.grad(loss(w, b), (w, b)))

    return [w0, b0], loss, grad_fn


@pytest.mark.parametrize("no_prox,wd,max_norm", [(True, 0.0, 0.0), (True, 0.05, 0.3), (False, 0.05, 0.3)])
def test_adan_matches_reference_loop(no_prox, wd, max_norm):
    params0, loss, grad_fn = _problem()
    lrs = [0.05, 0.01]
    expected = reference_adan(params0, grad_fn, lrs, steps=6, wd=wd, max_norm=max_norm, no_prox=no_prox)
    w, b = (torch.nn.Parameter(p.clone()) for p in params0)
    opt = Adan(param_groups({"grid": [w], "mlp": [b]}, 0.01, {"grid": 5.0}), weight_decay=wd,
               max_grad_norm=max_norm, no_prox=no_prox)
    for _ in range(6):
        opt.zero_grad()
        loss(w, b).backward()
        opt.step()
    # tolerance: the library sums the clipping norm in fp32
    torch.testing.assert_close(w.detach(), expected[0], rtol=1e-7, atol=1e-9)
    torch.testing.assert_close(b.detach(), expected[1], rtol=1e-7, atol=1e-9)
    assert opt.applied_steps == 6 and opt.skipped_steps == 0


def test_non_finite_gradient_skips_and_counts_without_touching_state():
    w = torch.nn.Parameter(torch.ones(4))
    opt = Adan([w], lr=0.1)
    (w ** 2).sum().backward()
    opt.step()
    state = {k: v.clone() for k, v in opt.state[w].items() if torch.is_tensor(v)}
    before = w.detach().clone()
    for bad in (float("nan"), float("inf")):
        w.grad = torch.ones(4)
        w.grad[2] = bad
        assert not opt.grads_finite() and not grads_finite([w])
        opt.step()
    assert opt.skipped_steps == 2 and opt.applied_steps == 1
    assert torch.equal(w.detach(), before)
    for k, v in state.items():
        assert torch.equal(opt.state[w][k], v)


def test_per_group_rates_follow_schedule_factor():
    a, b = torch.nn.Parameter(torch.zeros(2)), torch.nn.Parameter(torch.zeros(2))
    frozen = torch.nn.Parameter(torch.zeros(2), requires_grad=False)
    groups = param_groups({"grid": [a], "mlp": [b, frozen], "feature": [frozen]}, OFFICIAL_LR, OFFICIAL_MULTIPLIERS)
    assert [g["name"] for g in groups] == ["grid", "mlp"]
    opt = Adan(groups)
    assert [g["lr"] for g in opt.param_groups] == pytest.approx([5e-2, 5e-3])
    opt.set_lr_factor(0.1)
    assert [g["lr"] for g in opt.param_groups] == pytest.approx([5e-3, 5e-4])
