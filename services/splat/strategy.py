"""Densification as a strategy dataclass (after gsplat's `DefaultStrategy`, the 3DGS recipe).

    strategy = DefaultStrategy(refine_stop_iter=15_000)
    state = strategy.initialize_state(scene_scale)
    ...  render -> info
    strategy.step_pre_backward(params, optimizers, state, step, info)
    loss.backward(); optimizers step
    strategy.step_post_backward(params, optimizers, state, step, info)

Every `refine_every` steps between `refine_start_iter` and `refine_stop_iter`, Gaussians whose view-space
positional gradient (averaged over the views that saw them, in NDC units) exceeds `grow_grad2d` are cloned
when small (max scale <= grow_scale3d * scene_scale) or split in two when large; Gaussians below
`prune_opa` opacity, and (after the first opacity reset) those larger than prune_scale3d * scene_scale,
are removed. Every `reset_every` steps the opacities are reset to at most 2 * prune_opa.
The optimizers (one Adam per parameter) have their moments cut, copied or zeroed alongside.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch

from .projection import quat_to_rotmat


@torch.no_grad()
def _update_params(
    params: torch.nn.ParameterDict,
    optimizers: dict[str, torch.optim.Optimizer],
    param_fn: Callable[[str, torch.Tensor], torch.Tensor],
    state_fn: Callable[[str, torch.Tensor], torch.Tensor],
    names: list[str] | None = None,
) -> None:
    """Replace each parameter p by param_fn(name, p) and each optimizer moment v by state_fn(key, v)."""
    for name in names or list(params.keys()):
        old = params[name]
        new = torch.nn.Parameter(param_fn(name, old), requires_grad=old.requires_grad)
        params[name] = new
        opt = optimizers.get(name)
        if opt is None:
            continue
        for group in opt.param_groups:
            if group["params"][0] is not old:
                continue
            st = opt.state.pop(old, None)
            if st:
                for k, v in st.items():
                    if k != "step" and torch.is_tensor(v) and v.shape[:1] == old.shape[:1]:
                        st[k] = state_fn(k, v)
                opt.state[new] = st
            group["params"] = [new]


@torch.no_grad()
def duplicate(params, optimizers, state: dict, mask: torch.Tensor) -> None:
    """Clone the Gaussians selected by `mask` (N,) bool (appended at the end; moments zero)."""
    sel = torch.nonzero(mask)[:, 0]
    _update_params(
        params,
        optimizers,
        lambda _, p: torch.cat([p, p[sel]]),
        lambda _, v: torch.cat([v, torch.zeros_like(v[sel])]),
    )
    for k, v in state.items():
        if torch.is_tensor(v) and v.dim() > 0:
            state[k] = torch.cat([v, v[sel]])


@torch.no_grad()
def split(params, optimizers, state: dict, mask: torch.Tensor) -> None:
    """Replace each Gaussian selected by `mask` by two, sampled inside it, with scales / 1.6."""
    sel = torch.nonzero(mask)[:, 0]
    rest = torch.nonzero(~mask)[:, 0]
    scales = torch.exp(params["scales"][sel])
    R = quat_to_rotmat(params["quats"][sel])
    noise = torch.randn(2, len(sel), 3).to(scales)  # drawn on the CPU: the same stream on every device
    samples = torch.einsum("nij,bnj->bni", R, scales * noise)  # (2, n, 3)

    def param_fn(name: str, p: torch.Tensor) -> torch.Tensor:
        if name == "means":
            new = (p[sel] + samples).reshape(-1, 3)
        elif name == "scales":
            new = torch.log(scales / 1.6).repeat(2, 1)
        else:
            new = p[sel].repeat(2, *[1] * (p.dim() - 1))
        return torch.cat([p[rest], new])

    _update_params(
        params,
        optimizers,
        param_fn,
        lambda _, v: torch.cat([v[rest], v.new_zeros((2 * len(sel), *v.shape[1:]))]),
    )
    for k, v in state.items():
        if torch.is_tensor(v) and v.dim() > 0:
            state[k] = torch.cat([v[rest], v[sel].repeat(2, *[1] * (v.dim() - 1))])


@torch.no_grad()
def remove(params, optimizers, state: dict, mask: torch.Tensor) -> None:
    """Delete the Gaussians selected by `mask`."""
    keep = torch.nonzero(~mask)[:, 0]
    _update_params(params, optimizers, lambda _, p: p[keep], lambda _, v: v[keep])
    for k, v in state.items():
        if torch.is_tensor(v) and v.dim() > 0:
            state[k] = v[keep]


@torch.no_grad()
def reset_opacities(params, optimizers, value: float) -> None:
    """Clamp opacities to at most `value` and zero their optimizer moments."""
    logit = math.log(value / (1 - value))
    _update_params(
        params, optimizers, lambda _, p: p.clamp_max(logit), lambda _, v: torch.zeros_like(v), ["opacities"]
    )


@dataclass
class DefaultStrategy:
    """The 3DGS densification schedule (defaults are the paper's for 30k steps)."""

    prune_opa: float = 0.005
    grow_grad2d: float = 0.0002
    grow_scale3d: float = 0.01
    grow_scale2d: float = 0.05
    prune_scale3d: float = 0.1
    prune_scale2d: float = 0.15
    refine_scale2d_stop_iter: int = 0
    refine_start_iter: int = 500
    refine_stop_iter: int = 15_000
    reset_every: int = 3000
    refine_every: int = 100
    pause_refine_after_reset: int = 0
    max_gaussians: int = 0  # 0: unlimited; else no growth beyond this count
    verbose: bool = False

    def initialize_state(self, scene_scale: float = 1.0) -> dict[str, Any]:
        return {"grad2d": None, "count": None, "radii": None, "scene_scale": scene_scale}

    def step_pre_backward(self, params, optimizers, state: dict, step: int, info: dict) -> None:
        """Keep the gradient of the 2D means (read after backward)."""
        if step < self.refine_stop_iter and info["means2d"].requires_grad:
            info["means2d"].retain_grad()

    def step_post_backward(self, params, optimizers, state: dict, step: int, info: dict) -> dict[str, int]:
        """Accumulate statistics, then grow / prune / reset when due. Returns counts of what changed."""
        out: dict[str, int] = {}
        if step >= self.refine_stop_iter or len(params["means"]) == 0:  # nothing left to refine
            return out
        self._update_state(params, state, info)
        if (
            step > self.refine_start_iter
            and step % self.refine_every == 0
            and step % self.reset_every >= self.pause_refine_after_reset
        ):
            out["duplicated"], out["split"] = self._grow(params, optimizers, state, step)
            out["pruned"] = self._prune(params, optimizers, state, step)
            z = torch.zeros_like(params["opacities"]).detach()
            state["grad2d"], state["count"] = z.clone(), z.clone()
            state["radii"] = z.clone() if self.refine_scale2d_stop_iter > 0 else None
        if step % self.reset_every == 0 and step > 0:
            reset_opacities(params, optimizers, value=self.prune_opa * 2.0)
            out["reset"] = 1
        return out

    @torch.no_grad()
    def _update_state(self, params, state: dict, info: dict) -> None:
        n = len(params["means"])
        z = torch.zeros_like(params["opacities"]).detach()
        if state["grad2d"] is None or len(state["grad2d"]) != n:
            state["grad2d"], state["count"] = z.clone(), z.clone()
        if self.refine_scale2d_stop_iter > 0 and (state["radii"] is None or len(state["radii"]) != n):
            state["radii"] = z.clone()
        m2 = info["means2d"]
        if m2.grad is None:
            return
        grads = m2.grad.detach().reshape(n, 2).float().clone()
        grads[:, 0] *= info["width"] / 2.0 * info["n_cameras"]  # pixels -> NDC (the paper's units)
        grads[:, 1] *= info["height"] / 2.0 * info["n_cameras"]
        radii = info["radii"].detach().reshape(n, -1)
        sel = (radii > 0).all(-1)
        ids = torch.nonzero(sel)[:, 0]
        state["grad2d"].index_add_(0, ids, grads[ids].norm(dim=-1).to(z))
        state["count"].index_add_(0, ids, torch.ones_like(ids, dtype=z.dtype))
        if self.refine_scale2d_stop_iter > 0:
            r = radii[ids].max(-1).values.float() / float(max(info["width"], info["height"]))
            state["radii"][ids] = torch.maximum(state["radii"][ids], r.to(z))

    @torch.no_grad()
    def _grow(self, params, optimizers, state: dict, step: int) -> tuple[int, int]:
        grads = state["grad2d"] / state["count"].clamp_min(1)
        high = grads > self.grow_grad2d
        small = torch.exp(params["scales"]).max(-1).values <= self.grow_scale3d * state["scene_scale"]
        is_dupli = high & small
        is_split = high & ~small
        if step < self.refine_scale2d_stop_iter:
            is_split |= state["radii"] > self.grow_scale2d
        if self.max_gaussians > 0:  # keep the highest gradients within the budget
            room = self.max_gaussians - len(grads)
            want = int(is_dupli.sum()) + int(is_split.sum())
            if want > room:
                grow = is_dupli | is_split
                keep = torch.zeros_like(grow)
                if room > 0:
                    keep[torch.argsort(torch.where(grow, grads, -1.0), descending=True)[:room]] = True
                is_dupli, is_split = is_dupli & keep, is_split & keep
        n_dupli, n_split = int(is_dupli.sum()), int(is_split.sum())
        if n_dupli:
            duplicate(params, optimizers, state, is_dupli)
        is_split = torch.cat([is_split, is_split.new_zeros(n_dupli)])
        if n_split:
            split(params, optimizers, state, is_split)
        return n_dupli, n_split

    @torch.no_grad()
    def _prune(self, params, optimizers, state: dict, step: int) -> int:
        is_prune = torch.sigmoid(params["opacities"]) < self.prune_opa
        if step > self.reset_every:
            too_big = torch.exp(params["scales"]).max(-1).values > self.prune_scale3d * state["scene_scale"]
            if step < self.refine_scale2d_stop_iter:
                too_big |= state["radii"] > self.prune_scale2d
            is_prune |= too_big
        n = int(is_prune.sum())
        if n:
            remove(params, optimizers, state, is_prune)
        return n
