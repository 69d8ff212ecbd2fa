"""Numba kernels of the CPU tile rasterizer (float32).

Per-Gaussian data are packed as rows of `gdata` (N, 6 + C): mean x, mean y, conic a, b, c, opacity,
then C colour channels. Tiles are 16 x 16 pixels; `gids[offsets[t]:offsets[t + 1]]` lists the Gaussians
touching tile t front to back. Both passes run over tiles in parallel and, inside a tile, over Gaussians
in depth order, visiting only the pixels of each Gaussian's rectangle (so the work is proportional to the
pixels actually covered). The backward pass writes one gradient row per (tile, Gaussian) intersection,
summed per Gaussian afterwards in a fixed order: the result does not depend on the number of threads.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from ..projection import ALPHA_MAX, ALPHA_MIN, T_MIN

TILE = 16
NPIX = TILE * TILE
_AMIN = np.float32(ALPHA_MIN)
_AMAX = np.float32(ALPHA_MAX)
_TMIN = np.float32(T_MIN)


@njit(inline="always", fastmath=True)
def _row(a, b, c, L, mx, dy, x0, x1):
    """Span [xs, xe) of the pixels of one row (offset dy from the mean) where the Gaussian can reach
    ALPHA_MIN, widened by a pixel on each side and clipped to [x0, x1), with the Gaussian's value G at
    xs and the ratio R = G(x + 1) / G(x) there. Along a row log G is a parabola in x: G is updated by
    G *= R, R *= exp(-a) (two products per pixel instead of an exp). L = log(opacity / ALPHA_MIN)."""
    D = (b * dy) * (b * dy) - a * (c * dy * dy - np.float32(2.0) * L)
    if D < 0 or L <= 0:
        return 0, 0, np.float32(0.0), np.float32(0.0)
    sq = math.sqrt(D)
    xs = max(x0, int(math.floor(mx + (-b * dy - sq) / a - np.float32(0.5))))
    xe = min(x1, int(math.floor(mx + (-b * dy + sq) / a - np.float32(0.5))) + 2)
    if xs >= xe:
        return 0, 0, np.float32(0.0), np.float32(0.0)
    dx = np.float32(xs) + np.float32(0.5) - mx
    G = math.exp(np.float32(-0.5) * (a * dx * dx + c * dy * dy) - b * dx * dy)
    R = math.exp(-a * dx - np.float32(0.5) * a - b * dy)
    return xs, xe, G, R


@njit(cache=True)
def bin_gaussians(rects, order, tiles_x, tiles_y):
    """rects (N, 4) int32 pixel ranges, order (M,) Gaussian ids front to back ->
    offsets (tiles + 1,) int64, gids (n_isect,) int32 sorted by tile then depth."""
    n_tiles = tiles_x * tiles_y
    offsets = np.zeros(n_tiles + 1, np.int64)
    for i in range(order.shape[0]):
        g = order[i]
        for ty in range(rects[g, 1] // TILE, (rects[g, 3] - 1) // TILE + 1):
            for tx in range(rects[g, 0] // TILE, (rects[g, 2] - 1) // TILE + 1):
                offsets[ty * tiles_x + tx + 1] += 1
    for t in range(n_tiles):
        offsets[t + 1] += offsets[t]
    cursor = offsets[:-1].copy()
    gids = np.empty(offsets[n_tiles], np.int32)
    for i in range(order.shape[0]):
        g = order[i]
        for ty in range(rects[g, 1] // TILE, (rects[g, 3] - 1) // TILE + 1):
            for tx in range(rects[g, 0] // TILE, (rects[g, 2] - 1) // TILE + 1):
                t = ty * tiles_x + tx
                gids[cursor[t]] = g
                cursor[t] += 1
    return offsets, gids


@njit(parallel=True, fastmath=True, cache=True)
def rasterize_fwd(gdata, rects, gids, offsets, width, height, tiles_x, bg, tile_order):
    """-> color (H, W, C), final transmittance (H, W), last contributing intersection (H, W) (-1: none).
    Tiles are visited in `tile_order` (a permutation: threads get equal shares of busy and empty tiles)."""
    C = gdata.shape[1] - 6
    out = np.empty((height, width, C), np.float32)
    out_T = np.empty((height, width), np.float32)
    out_last = np.empty((height, width), np.int32)
    for i in prange(tile_order.shape[0]):
        t = tile_order[i]
        X0 = (t % tiles_x) * TILE
        Y0 = (t // tiles_x) * TILE
        X1 = min(X0 + TILE, width)
        Y1 = min(Y0 + TILE, height)
        npix = (X1 - X0) * (Y1 - Y0)
        T = np.ones(NPIX, np.float32)
        acc = np.zeros((NPIX, C), np.float32)
        last = np.full(NPIX, -1, np.int32)
        done = np.zeros(NPIX, np.bool_)
        n_done = 0
        for k in range(offsets[t], offsets[t + 1]):
            g = gids[k]
            mx, my = gdata[g, 0], gdata[g, 1]
            a, b, c, o = gdata[g, 2], gdata[g, 3], gdata[g, 4], gdata[g, 5]
            Q = math.exp(-a)
            L = math.log(o / _AMIN)
            x0, x1 = max(rects[g, 0], X0), min(rects[g, 2], X1)
            for y in range(max(rects[g, 1], Y0), min(rects[g, 3], Y1)):
                dy = np.float32(y) + np.float32(0.5) - my
                xs, xe, Gn, R = _row(a, b, c, L, mx, dy, x0, x1)
                row = (y - Y0) * TILE - X0
                for x in range(xs, xe):
                    G = Gn
                    Gn *= R
                    R *= Q
                    p = row + x
                    if done[p]:
                        continue
                    alpha = o * G
                    if alpha < _AMIN:
                        continue
                    alpha = min(alpha, _AMAX)
                    nT = T[p] * (np.float32(1.0) - alpha)
                    if nT < _TMIN:
                        done[p] = True
                        n_done += 1
                        continue
                    w = alpha * T[p]
                    for ch in range(C):
                        acc[p, ch] += w * gdata[g, 6 + ch]
                    T[p] = nT
                    last[p] = k
            if n_done == npix:
                break
        for y in range(Y0, Y1):
            for x in range(X0, X1):
                p = (y - Y0) * TILE + x - X0
                for ch in range(C):
                    out[y, x, ch] = acc[p, ch] + T[p] * bg[ch]
                out_T[y, x] = T[p]
                out_last[y, x] = last[p]
    return out, out_T, out_last


@njit(inline="always", fastmath=True)
def _bwd_tile(final_T, last, v_color, v_alpha, bg, X0, Y0, X1, Y1, C):
    """One tile's state for the backward pass, per pixel: transmittance (running and final), colour
    behind the current Gaussian (background included), the loss gradients, the last Gaussian; and the
    largest of those."""
    T = np.ones(NPIX, np.float32)
    Tf = np.ones(NPIX, np.float32)
    S = np.zeros((NPIX, C), np.float32)
    vC = np.zeros((NPIX, C), np.float32)
    vA = np.zeros(NPIX, np.float32)
    lst = np.full(NPIX, -1, np.int64)
    kmax = -1
    for y in range(Y0, Y1):
        for x in range(X0, X1):
            p = (y - Y0) * TILE + x - X0
            T[p] = final_T[y, x]
            Tf[p] = final_T[y, x]
            vA[p] = v_alpha[y, x]
            lst[p] = last[y, x]
            kmax = max(kmax, lst[p])
            for ch in range(C):
                S[p, ch] = bg[ch]
                vC[p, ch] = v_color[y, x, ch]
    return T, Tf, S, vC, vA, lst, kmax


@njit(inline="always", fastmath=True)
def _bwd_gaussian(k, g, gdata, rects, X0, Y0, X1, Y1, C, T, Tf, S, vC, vA, lst, gcol, grads):
    """Intersection k (Gaussian g) of a tile, back to front: its gradients into grads[k], the tile's
    transmittance and colour-behind rolled back past it."""
    mx, my = gdata[g, 0], gdata[g, 1]
    a, b, c, o = gdata[g, 2], gdata[g, 3], gdata[g, 4], gdata[g, 5]
    x0, x1 = max(rects[g, 0], X0), min(rects[g, 2], X1)
    gmx = np.float32(0.0)
    gmy = np.float32(0.0)
    ga = np.float32(0.0)
    gb = np.float32(0.0)
    gc = np.float32(0.0)
    go = np.float32(0.0)
    gcol[:] = 0
    Q = math.exp(-a)
    L = math.log(o / _AMIN)
    for y in range(max(rects[g, 1], Y0), min(rects[g, 3], Y1)):
        dy = np.float32(y) + np.float32(0.5) - my
        xs, xe, Gn, R = _row(a, b, c, L, mx, dy, x0, x1)
        row = (y - Y0) * TILE - X0
        r0 = np.float32(0.0)  # sums over the row of vp, vp dx, vp dx^2 (dy is constant)
        r1 = np.float32(0.0)
        r2 = np.float32(0.0)
        for x in range(xs, xe):
            G = Gn
            Gn *= R
            R *= Q
            p = row + x
            if k > lst[p]:
                continue
            raw = o * G
            if raw < _AMIN:
                continue
            dx = np.float32(x) + np.float32(0.5) - mx
            alpha = min(raw, _AMAX)
            om = np.float32(1.0) - alpha
            inv = np.float32(1.0) / om
            Ti = T[p] * inv
            T[p] = Ti
            w = alpha * Ti
            v_a = np.float32(0.0)
            for ch in range(C):
                col = gdata[g, 6 + ch]
                gcol[ch] += w * vC[p, ch]
                v_a += (col - S[p, ch]) * vC[p, ch]
                S[p, ch] = alpha * col + om * S[p, ch]
            v_a = v_a * Ti + vA[p] * Tf[p] * inv
            if raw <= _AMAX:  # (clamped alphas pass no gradient)
                go += G * v_a
                vp = raw * v_a  # d loss / d power
                vpx = vp * dx
                r0 += vp
                r1 += vpx
                r2 += vpx * dx
        # power = -(a dx^2 + c dy^2) / 2 - b dx dy with dx = x + 0.5 - mean x
        ga += np.float32(-0.5) * r2
        gb -= dy * r1
        gc += np.float32(-0.5) * dy * dy * r0
        gmx += a * r1 + b * dy * r0
        gmy += b * r1 + c * dy * r0
    grads[k, 0] = gmx
    grads[k, 1] = gmy
    grads[k, 2] = ga
    grads[k, 3] = gb
    grads[k, 4] = gc
    grads[k, 5] = go
    for ch in range(C):
        grads[k, 6 + ch] = gcol[ch]


@njit(parallel=True, fastmath=True, cache=True)
def rasterize_bwd(
    gdata, rects, gids, offsets, width, height, tiles_x, bg, tile_order, final_T, last, v_color, v_alpha
):
    """Gradients per intersection (n_isect, 6 + C) w.r.t. mean x, y, conic a, b, c, opacity, colours,
    given the loss gradients v_color (H, W, C) and v_alpha (H, W) of the outputs color and 1 - final_T."""
    C = gdata.shape[1] - 6
    grads = np.zeros((gids.shape[0], 6 + C), np.float32)
    for i in prange(tile_order.shape[0]):
        t = tile_order[i]
        if offsets[t + 1] == offsets[t]:
            continue
        X0 = (t % tiles_x) * TILE
        Y0 = (t // tiles_x) * TILE
        X1 = min(X0 + TILE, width)
        Y1 = min(Y0 + TILE, height)
        T, Tf, S, vC, vA, lst, kmax = _bwd_tile(final_T, last, v_color, v_alpha, bg, X0, Y0, X1, Y1, C)
        gcol = np.zeros(C, np.float32)
        for k in range(kmax, offsets[t] - 1, -1):
            _bwd_gaussian(k, gids[k], gdata, rects, X0, Y0, X1, Y1, C, T, Tf, S, vC, vA, lst, gcol, grads)
    return grads


@njit(cache=True)
def sum_per_gaussian(grads, gids, n):
    """Sum intersection rows into (n, D) rows per Gaussian, in intersection order."""
    out = np.zeros((n, grads.shape[1]), np.float32)
    for k in range(gids.shape[0]):
        g = gids[k]
        for j in range(grads.shape[1]):
            out[g, j] += grads[k, j]
    return out


@njit(parallel=True, fastmath=True, cache=True)
def separable_blur(x, w):
    """x (K, H, W) float32 filtered by the symmetric 1D kernel w (2r + 1,) along rows, then columns, with
    zero padding ("same" size). The filter is its own adjoint, so the backward pass calls it on the
    output gradient. Inner loops run along rows of zero-padded copies (vectorised)."""
    K, H, W = x.shape
    r = w.shape[0] // 2
    out = np.empty_like(x)
    for c in prange(K):
        pad = np.zeros(W + 2 * r, np.float32)
        tmp = np.zeros((H + 2 * r, W), np.float32)  # the row-filtered image between r zero rows
        for y in range(H):
            pad[r : r + W] = x[c, y]
            row = tmp[y + r]
            for k in range(2 * r + 1):
                wk = w[k]
                for i in range(W):
                    row[i] += wk * pad[i + k]
        for y in range(H):
            o = out[c, y]
            o[:] = 0
            for k in range(2 * r + 1):
                wk = w[k]
                t = tmp[y + k]
                for i in range(W):
                    o[i] += wk * t[i]
    return out
