"""Plain-PyTorch tile rasterizer: the test oracle for the compiled backends.

Every pixel composites the Gaussians whose pixel rectangle (`projection.pixel_rects`) holds it, front to
back in depth order: alpha = min(ALPHA_MAX, o * exp(-d^T conic d / 2)), skipped below ALPHA_MIN, and
compositing stops before the transmittance would fall below T_MIN (the 3DGS rules). Gradients come from
autograd. Slow and memory hungry (tiles are padded to their longest list), but simple.
"""

from __future__ import annotations

import torch

from .projection import ALPHA_MAX, ALPHA_MIN, T_MIN, pixel_rects

TILE = 16


def depth_order(depths: torch.Tensor, rects: torch.Tensor) -> torch.Tensor:
    """Indices of the Gaussians with a non-empty rectangle, front to back (stable: ties by index)."""
    ids = torch.nonzero(rects[:, 2] > rects[:, 0])[:, 0]
    return ids[torch.argsort(depths.detach()[ids], stable=True)]


def tile_intersections(
    rects: torch.Tensor, order: torch.Tensor, width: int, height: int, tile: int = TILE
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(tile id, Gaussian id) pairs sorted by tile, then depth: tile_ids (M,), gauss_ids (M,),
    tile_offsets (n_tiles + 1,)."""
    tiles_x, tiles_y = -(-width // tile), -(-height // tile)
    r = rects[order].long()
    tx0, ty0 = r[:, 0] // tile, r[:, 1] // tile
    ntx, nty = (r[:, 2] - 1) // tile + 1 - tx0, (r[:, 3] - 1) // tile + 1 - ty0
    cnt = ntx * nty
    rank = torch.repeat_interleave(torch.arange(len(order)), cnt)
    local = torch.arange(int(cnt.sum())) - torch.repeat_interleave(torch.cumsum(cnt, 0) - cnt, cnt)
    tid = (ty0[rank] + local // ntx[rank]) * tiles_x + tx0[rank] + local % ntx[rank]
    perm = torch.argsort(tid, stable=True)
    tid = tid[perm]
    counts = torch.bincount(tid, minlength=tiles_x * tiles_y)
    offsets = torch.cat([torch.zeros(1, dtype=torch.long), torch.cumsum(counts, 0)])
    return tid, order[rank[perm]], offsets


def rasterize_reference(
    means2d: torch.Tensor,
    conics: torch.Tensor,
    colors: torch.Tensor,
    opacities: torch.Tensor,
    depths: torch.Tensor,
    radii: torch.Tensor,
    width: int,
    height: int,
    backgrounds: torch.Tensor | None = None,
    max_elems: int = 1 << 22,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Alpha-composite projected Gaussians.

    means2d (N, 2), conics (N, 3), colors (N, C), opacities (N,), depths (N,), radii (N, 2) int,
    backgrounds (C,) or None (black). Returns render_colors (H, W, C) and render_alphas (H, W, 1).
    """
    dev, dt = means2d.device, means2d.dtype
    C = colors.shape[-1]
    P = TILE * TILE
    tiles_x, tiles_y = -(-width // TILE), -(-height // TILE)
    n_tiles = tiles_x * tiles_y
    rects = pixel_rects(means2d, radii, width, height)
    order = depth_order(depths, rects)
    _, gids, offsets = tile_intersections(rects, order, width, height)
    counts = offsets[1:] - offsets[:-1]
    local = torch.arange(P, device=dev)
    tile_col = [torch.zeros(0, P, C, dtype=dt, device=dev)]
    tile_T = [torch.zeros(0, P, dtype=dt, device=dev)]
    done = [torch.zeros(0, dtype=torch.long, device=dev)]
    nonempty = torch.nonzero(counts > 0)[:, 0]
    nonempty = nonempty[torch.argsort(counts[nonempty], stable=True)]
    i = 0
    while i < len(nonempty):  # batches of tiles of similar list length, padded to the longest
        j = i + 1
        while j < len(nonempty) and (j + 1 - i) * P * int(counts[nonempty[j]]) <= max_elems:
            j += 1
        tiles = nonempty[i:j]
        L = int(counts[tiles].max())
        slot = torch.arange(L, device=dev)
        valid = slot[None, :] < counts[tiles][:, None]  # (B, L)
        g = gids[(offsets[tiles][:, None] + slot[None, :]).clamp_max(len(gids) - 1)]  # (B, L)
        px = (tiles % tiles_x)[:, None] * TILE + local % TILE  # (B, P) pixel column
        py = (tiles // tiles_x)[:, None] * TILE + local // TILE
        r = rects[g]  # (B, L, 4)
        inside = (
            valid[:, None, :]
            & (px[:, :, None] >= r[:, None, :, 0])
            & (px[:, :, None] < r[:, None, :, 2])
            & (py[:, :, None] >= r[:, None, :, 1])
            & (py[:, :, None] < r[:, None, :, 3])
        )  # (B, P, L)
        dx = (px.to(dt) + 0.5)[:, :, None] - means2d[g][:, None, :, 0]
        dy = (py.to(dt) + 0.5)[:, :, None] - means2d[g][:, None, :, 1]
        cg = conics[g]
        power = (
            -0.5 * (cg[:, None, :, 0] * dx * dx + cg[:, None, :, 2] * dy * dy) - cg[:, None, :, 1] * dx * dy
        )
        inside = inside & (power <= 0)
        power = torch.where(inside, power, torch.full_like(power, -100.0))
        raw = opacities[g][:, None, :] * torch.exp(power)
        alpha = torch.where(inside & (raw >= ALPHA_MIN), raw.clamp_max(ALPHA_MAX), torch.zeros_like(raw))
        with torch.no_grad():
            keep = torch.cumprod(1 - alpha, -1) >= T_MIN
        alpha = torch.where(keep, alpha, torch.zeros_like(alpha))
        cp = torch.cumprod(1 - alpha, -1)
        T = torch.cat([torch.ones_like(cp[..., :1]), cp[..., :-1]], -1)
        tile_col.append(torch.einsum("bpl,blc->bpc", alpha * T, colors[g]))
        tile_T.append(cp[..., -1])
        done.append(tiles)
        i = j
    done = torch.cat(done)
    col = torch.zeros(n_tiles, P, C, dtype=dt, device=dev).index_copy(0, done, torch.cat(tile_col))
    Tf = torch.ones(n_tiles, P, dtype=dt, device=dev).index_copy(0, done, torch.cat(tile_T))
    if backgrounds is not None:
        col = col + Tf[..., None] * backgrounds
    col = col.reshape(tiles_y, tiles_x, TILE, TILE, C).permute(0, 2, 1, 3, 4).reshape(tiles_y * TILE, -1, C)
    Tf = Tf.reshape(tiles_y, tiles_x, TILE, TILE).permute(0, 2, 1, 3).reshape(tiles_y * TILE, -1)
    return col[:height, :width], (1 - Tf[:height, :width])[..., None]
