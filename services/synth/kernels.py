"""The numba renderer: hashed value noise, analytic ray casting of boxes, spheres and the ground plane
through a uniform 2-D grid, procedural materials with analytic anti-aliasing, sun + sky lighting.

All textures are functions of the hit point (world or face coordinates), so every view sees the same
detail. Noise octaves finer than twice the pixel footprint on the surface are left out (the last one
faded), periodic lines (mortar, grout, slats) are box-filtered analytically over the footprint, and
`render` supersamples each pixel on an ss x ss grid. Depth comes from the pixel's centre ray.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from .materials import (
    L_AMB,
    L_CLOUD,
    L_HAZEC,
    L_HAZED,
    L_HOR,
    L_SHADOW,
    L_SUN,
    L_SUNC,
    L_ZEN,
    MAT_BUILDING,
    MAT_BUSH,
    MAT_CAR,
    MAT_KERB,
    MAT_KIOSK,
    MAT_POLE,
    MAT_ROOFBOX,
    MAT_TRUNK,
    P_AXIS,
    P_B,
    P_B2,
    P_BAY,
    P_DOOR,
    P_FB,
    P_FG,
    P_FLOOR,
    P_FR,
    P_G,
    P_G2,
    P_GFLOOR,
    P_PARAPET,
    P_PHOTO,
    P_R,
    P_R2,
    P_RELIEF,
    P_ROOF,
    P_SEED,
    P_SHOP,
    P_STYLE,
    P_WALL,
    P_WALL_M,
    P_WINH,
    P_WINW,
    P_Z0,
    Z_FIELD,
    Z_GRASS,
    Z_PARKING,
    Z_PAVED,
    Z_ROAD,
    Z_SIDEWALK,
)

_M32 = 0xFFFFFFFF
_INV32 = 1.0 / 4294967296.0
_EPS = 1e-5
_INF = 1e30

# ---------------------------------------------------------------------------------------- hashing


@njit(cache=True, inline="always")
def hash4(a, b, c, d):
    """32-bit integer hash of four int64 -> int64 in [0, 2^32)."""
    h = (a * 73856093) ^ (b * 19349663) ^ (c * 83492791) ^ (d * 50331653)
    h = h & _M32
    h ^= h >> 16
    h = (h * 0x7FEB352D) & _M32
    h ^= h >> 15
    h = (h * 0x6B43A9B5) & _M32
    h ^= h >> 16
    return h


@njit(cache=True, inline="always")
def hashf(a, b, c, d):
    """Hash of four int64 -> float in [0, 1)."""
    return hash4(a, b, c, d) * _INV32


@njit(cache=True)
def mix(a, b, t):
    return a + (b - a) * t


_G2 = np.array([[math.cos(2 * math.pi * k / 16), math.sin(2 * math.pi * k / 16)] for k in range(16)])
_G3 = np.array(
    [[1, 1, 0], [-1, 1, 0], [1, -1, 0], [-1, -1, 0], [1, 0, 1], [-1, 0, 1], [1, 0, -1], [-1, 0, -1],
     [0, 1, 1], [0, -1, 1], [0, 1, -1], [0, -1, -1], [1, 1, 0], [-1, 1, 0], [0, -1, 1], [0, -1, -1]],
    np.float64,
)  # fmt: skip
# per-octave rotations, so that the lattices of successive octaves do not line up
_ROT = np.array([[math.cos(0.61 * k + 0.3), math.sin(0.61 * k + 0.3)] for k in range(24)])


@njit(cache=True)
def gnoise2(x, y, s):
    """2-D gradient (Perlin) noise, unit lattice, seed s; roughly in [-1, 1], std ~0.3."""
    xf = math.floor(x)
    yf = math.floor(y)
    ix = np.int64(xf)
    iy = np.int64(yf)
    fx = x - xf
    fy = y - yf
    ux = fx * fx * fx * (fx * (fx * 6.0 - 15.0) + 10.0)
    uy = fy * fy * fy * (fy * (fy * 6.0 - 15.0) + 10.0)
    h = hash4(ix, iy, s, 1) & 15
    a = _G2[h, 0] * fx + _G2[h, 1] * fy
    h = hash4(ix + 1, iy, s, 1) & 15
    b = _G2[h, 0] * (fx - 1.0) + _G2[h, 1] * fy
    h = hash4(ix, iy + 1, s, 1) & 15
    c = _G2[h, 0] * fx + _G2[h, 1] * (fy - 1.0)
    h = hash4(ix + 1, iy + 1, s, 1) & 15
    d = _G2[h, 0] * (fx - 1.0) + _G2[h, 1] * (fy - 1.0)
    return 1.4 * (a + (b - a) * ux + (c - a) * uy + (a - b - c + d) * ux * uy)


@njit(cache=True)
def _g3(ix, iy, iz, s, x, y, z):
    h = hash4(ix, iy, iz, s) & 15
    return _G3[h, 0] * x + _G3[h, 1] * y + _G3[h, 2] * z


@njit(cache=True)
def gnoise3(x, y, z, s):
    """3-D gradient (Perlin) noise, unit lattice, seed s; roughly in [-1, 1]."""
    xf = math.floor(x)
    yf = math.floor(y)
    zf = math.floor(z)
    ix = np.int64(xf)
    iy = np.int64(yf)
    iz = np.int64(zf)
    fx = x - xf
    fy = y - yf
    fz = z - zf
    ux = fx * fx * fx * (fx * (fx * 6.0 - 15.0) + 10.0)
    uy = fy * fy * fy * (fy * (fy * 6.0 - 15.0) + 10.0)
    uz = fz * fz * fz * (fz * (fz * 6.0 - 15.0) + 10.0)
    s2 = s * 7919 + 3
    v0 = mix(_g3(ix, iy, iz, s2, fx, fy, fz), _g3(ix + 1, iy, iz, s2, fx - 1, fy, fz), ux)
    v1 = mix(_g3(ix, iy + 1, iz, s2, fx, fy - 1, fz), _g3(ix + 1, iy + 1, iz, s2, fx - 1, fy - 1, fz), ux)
    v2 = mix(_g3(ix, iy, iz + 1, s2, fx, fy, fz - 1), _g3(ix + 1, iy, iz + 1, s2, fx - 1, fy, fz - 1), ux)
    v3 = mix(
        _g3(ix, iy + 1, iz + 1, s2, fx, fy - 1, fz - 1),
        _g3(ix + 1, iy + 1, iz + 1, s2, fx - 1, fy - 1, fz - 1),
        ux,
    )
    return 1.1 * mix(mix(v0, v1, uy), mix(v2, v3, uy), uz)


@njit(cache=True)
def fade(lam, fp):
    """Weight of a detail of size lam seen with footprint fp: 1 above 4 fp, 0 below 2 fp."""
    w = lam / (2.0 * fp) - 1.0
    return 0.0 if w < 0.0 else (1.0 if w > 1.0 else w)


@njit(cache=True)
def fbm2(u, v, s, lam0, fp, lam_min, gain):
    """Multi-octave value noise, wavelengths lam0, lam0/2, ... >= max(lam_min, 2 fp), amplitudes gain^k.

    Octaves below twice the footprint fp are left out and the last one is faded (analytic anti-aliasing).
    Returns roughly N(0, 0.3^2 * sum gain^2k).
    """
    acc = 0.0
    amp = 1.0
    lam = lam0
    k = 0
    while k < 24 and lam >= lam_min:
        w = lam / (2.0 * fp) - 1.0
        if w <= 0.0:
            break
        if w > 1.0:
            w = 1.0
        x = u / lam
        y = v / lam
        acc += (
            amp * w * gnoise2(_ROT[k, 0] * x - _ROT[k, 1] * y, _ROT[k, 1] * x + _ROT[k, 0] * y, s * 131 + k)
        )
        amp *= gain
        lam *= 0.5
        k += 1
    return acc


@njit(cache=True)
def fbm3(x, y, z, s, lam0, fp, lam_min, gain):
    """3-D version of fbm2 (for curved surfaces)."""
    acc = 0.0
    amp = 1.0
    lam = lam0
    k = 0
    while k < 16 and lam >= lam_min:
        w = lam / (2.0 * fp) - 1.0
        if w <= 0.0:
            break
        if w > 1.0:
            w = 1.0
        acc += amp * w * gnoise3(x / lam + 0.37 * k, y / lam, z / lam, s * 131 + k)
        amp *= gain
        lam *= 0.5
        k += 1
    return acc


@njit(cache=True)
def _pint(x, p, w):
    n = math.floor(x / p)
    r = x - n * p
    return n * w + (r if r < w else w)


@njit(cache=True)
def lines(x, p, w, fp):
    """Coverage in [0, 1] of lines of width w centred on multiples of p, box-filtered over width fp."""
    x = x + 0.5 * w
    if fp < 1e-6:
        r = x - math.floor(x / p) * p
        return 1.0 if r < w else 0.0
    h = 0.5 * fp
    return (_pint(x + h, p, w) - _pint(x - h, p, w)) / fp


@njit(cache=True)
def band(x, lo, hi, fp):
    """Box-filtered indicator of the interval [lo, hi]."""
    if fp < 1e-6:
        return 1.0 if lo <= x <= hi else 0.0
    a = max(x - 0.5 * fp, lo)
    b = min(x + 0.5 * fp, hi)
    return max(b - a, 0.0) / fp


# ----------------------------------------------------------------------------------- photo textures


@njit(cache=True)
def spots(u, v, cell, p, rmin, rmax, fp, s):
    """Coverage in [0, 1] of sparse round spots (dirt, chips, chewing gum): at most one per cell x cell
    square, present with probability p, radius in [rmin, rmax]; edges filtered over fp, and the spots
    fade out once they are smaller than the footprint."""
    ci = np.int64(math.floor(u / cell))
    cj = np.int64(math.floor(v / cell))
    if hashf(ci, cj, s, 31) >= p:
        return 0.0
    r = rmin + (rmax - rmin) * hashf(ci, cj, s, 32)
    w = fade(2.0 * r, fp)
    if w <= 0.0:
        return 0.0
    cx = (ci + 0.5) * cell + (0.5 * cell - r) * (2.0 * hashf(ci, cj, s, 33) - 1.0)
    cy = (cj + 0.5) * cell + (0.5 * cell - r) * (2.0 * hashf(ci, cj, s, 34) - 1.0)
    e = (r - math.hypot(u - cx, v - cy)) / max(fp, 1e-4) + 0.5
    return w * min(max(e, 0.0), 1.0)


@njit(cache=True)
def _texel(atlas, aoff, adim, p, lev, x, y, c):
    h = adim[p, lev, 0]
    w = adim[p, lev, 1]
    xi = min(max(x, 0), w - 1)
    yi = min(max(y, 0), h - 1)
    return atlas[aoff[p, lev] + (yi * w + xi) * 3 + c]


@njit(cache=True)
def _bilinear(atlas, aoff, adim, lut, p, lev, s, t):
    sc = 1.0 / (1 << lev)
    x = s * sc - 0.5
    y = t * sc - 0.5
    x0 = math.floor(x)
    y0 = math.floor(y)
    fx = x - x0
    fy = y - y0
    xi = np.int64(x0)
    yi = np.int64(y0)
    r = 0.0
    g = 0.0
    b = 0.0
    for c in range(3):
        v00 = lut[_texel(atlas, aoff, adim, p, lev, xi, yi, c)]
        v10 = lut[_texel(atlas, aoff, adim, p, lev, xi + 1, yi, c)]
        v01 = lut[_texel(atlas, aoff, adim, p, lev, xi, yi + 1, c)]
        v11 = lut[_texel(atlas, aoff, adim, p, lev, xi + 1, yi + 1, c)]
        v = (v00 * (1 - fx) + v10 * fx) * (1 - fy) + (v01 * (1 - fx) + v11 * fx) * fy
        if c == 0:
            r = v
        elif c == 1:
            g = v
        else:
            b = v
    return r, g, b


@njit(cache=True)
def photo_sample(atlas, aoff, adim, lut, p, s, t, texel_m, fp):
    """Trilinear (mip-mapped) sample of photo p at level-0 texel coordinates (s, t)."""
    nlev = aoff.shape[1]
    lev = math.log2(max(fp / texel_m, 1.0))
    l0 = min(int(lev), nlev - 1)
    f = lev - l0
    r, g, b = _bilinear(atlas, aoff, adim, lut, p, l0, s, t)
    if f > 0.0 and l0 + 1 < nlev:
        r1, g1, b1 = _bilinear(atlas, aoff, adim, lut, p, l0 + 1, s, t)
        r, g, b = mix(r, r1, f), mix(g, g1, f), mix(b, b1, f)
    return r, g, b


@njit(cache=True)
def facade_photo(u, z, fp, cell_w, fs, atlas, aoff, adim, lut):
    """A facade tiled with photo crops: each cell (cell_w m wide) its own hashed photo, crop and flip."""
    nphoto = aoff.shape[0]
    h0 = adim[0, 0, 0]
    w0 = adim[0, 0, 1]
    cell_h = cell_w * h0 / w0
    cu = math.floor(u / cell_w)
    cv = math.floor(z / cell_h)
    iu = np.int64(cu)
    iv = np.int64(cv)
    p = np.int64(hashf(iu, iv, fs, 41) * nphoto)
    crop = 0.6 + 0.4 * hashf(iu, iv, fs, 42)
    ox = (1.0 - crop) * hashf(iu, iv, fs, 43)
    oy = (1.0 - crop) * hashf(iu, iv, fs, 44)
    fu = u / cell_w - cu
    fv = 1.0 - (z / cell_h - cv)
    if hashf(iu, iv, fs, 45) < 0.5:
        fu = 1.0 - fu
    s = (ox + fu * crop) * w0
    t = (oy + fv * crop) * h0
    return photo_sample(atlas, aoff, adim, lut, p, s, t, cell_w * crop / w0, fp)


@njit(cache=True)
def mirrored(x, n):
    """x folded into [0, n): tiles mirrored at every edge, so that neighbouring tiles meet seamlessly."""
    m = x % (2.0 * n)
    return m if m < n else 2.0 * n - m


@njit(cache=True)
def wall_photo(u, z, fp, par, atlas, aoff, adim, lut):
    """The wall photo par[P_WALL] (services.synth.walls) tiled over a facade at its scale par[P_WALL_M]."""
    p = np.int64(par[P_WALL])
    m = par[P_WALL_M]
    s = mirrored(u / m, adim[p, 0, 1] - 1.0)
    t = mirrored(-z / m, adim[p, 0, 0] - 1.0)
    return photo_sample(atlas, aoff, adim, lut, p, s, t, m, fp)


# ------------------------------------------------------------------------------------ materials


@njit(cache=True)
def window(x, y, ww, wh, fp, fs, bi, fl, fr, fg, fb):
    """A window centred at x = 0, sill at y = 0: (hit, r, g, b). Frame, mullion, transom, glass with
    per-window tint, blinds or curtains."""
    if y < -0.08 or y > wh or abs(x) > ww + 0.06:
        return False, 0.0, 0.0, 0.0
    if y < 0.0:  # sill
        return True, 0.55, 0.53, 0.5
    if abs(x) > ww:
        return False, 0.0, 0.0, 0.0
    fw = 0.07
    ax = abs(x)
    if ww - ax < fw or y < fw or wh - y < fw or ax < 0.035 or abs(y - 0.7 * wh) < 0.03:
        return True, fr, fg, fb
    h1 = hashf(bi, fl, fs, 101)
    h2 = hashf(bi, fl, fs, 102)
    h3 = hashf(bi, fl, fs, 103)
    # glass: dark interior + sky reflection brighter towards the top
    refl = (0.03 + 0.06 * (y / wh) + 0.05 * h2) * math.exp(
        0.5 * fbm2(x + 13.7 * bi, y + 7.9 * fl, fs * 7 + 3, 0.8, fp, 0.004, 0.8)
    )  # reflections and things behind the glass
    r = 0.02 + refl * 0.8
    g = 0.025 + refl * 0.9
    b = 0.03 + refl * (1.0 + 0.3 * h1)
    if h3 < 0.35:  # blinds from the top down to a hashed fraction
        bf = 0.2 + 0.8 * h2
        if y > wh * (1.0 - bf):
            slat = lines(y, 0.035, 0.006, fp)
            k = (0.85 + 0.15 * h1) * (1.0 - 0.45 * slat)
            return True, 0.62 * k, 0.6 * k, 0.55 * k
    elif h3 < 0.7:  # curtains on both sides
        cf = (0.15 + 0.3 * h1) * ww
        if ww - ax < cf:
            fold = 1.0 + 0.25 * math.sin(x * 69.8) * fade(0.09, fp)
            cr = 0.2 + 0.5 * hashf(bi, fl, fs, 104)
            cg = 0.15 + 0.45 * hashf(bi, fl, fs, 105)
            cb = 0.1 + 0.4 * hashf(bi, fl, fs, 106)
            return True, cr * fold, cg * fold, cb * fold
    return True, r, g, b


@njit(cache=True)
def shopfront(ub, v, bay, hg, fp, fs, bi):
    """A shop front in one ground-floor bay (ub centred, v from the ground): (hit, r, g, b)."""
    hw = 0.5 * bay - 0.08
    if abs(ub) > hw:
        return False, 0.0, 0.0, 0.0
    # sign band with hashed block letters
    if hg - 0.9 < v < hg - 0.2:
        sr = 0.1 + 0.6 * hashf(bi, 0, fs, 111)
        sg = 0.1 + 0.5 * hashf(bi, 0, fs, 112)
        sb = 0.1 + 0.5 * hashf(bi, 0, fs, 113)
        lw = hw * (0.5 + 0.4 * hashf(bi, 0, fs, 114))
        if abs(ub) < lw and hg - 0.8 < v < hg - 0.3:
            li = np.int64(math.floor(ub / 0.17))
            lj = np.int64(math.floor((v - hg + 0.8) / 0.125))
            inner = ub / 0.17 - li
            if 0.12 < inner < 0.88 and hashf(li, lj, fs * 31 + bi, 115) < 0.55:
                k = 0.95 if sr + sg + sb < 0.9 else 0.05
                return True, k, k * 0.95, k * 0.9
        return True, sr, sg, sb
    if v < 0.45:  # stall riser
        return True, 0.15, 0.15, 0.16
    if v > hg - 0.9:
        return False, 0.0, 0.0, 0.0
    fw = 0.06
    if hw - abs(ub) < fw or v < 0.45 + fw or (hg - 0.9) - v < fw:
        return True, 0.1, 0.1, 0.11
    # door in the shop front
    dx = (hashf(bi, 1, fs, 116) - 0.5) * (bay - 1.6)
    if abs(ub - dx) < 0.5 and v < 2.3:
        if abs(abs(ub - dx) - 0.5) < 0.05 or abs(v - 2.25) < 0.05:
            return True, 0.1, 0.1, 0.11
    # the shop inside: shelves every 0.45 m with goods of hashed colours and widths
    vs = v - 0.45
    row = np.int64(math.floor(vs / 0.45))
    shelf = band(vs - row * 0.45, -1.0, 0.04, fp)
    x = ub + bi * 7.3 + 0.37 * row
    ci = np.int64(math.floor(x / 0.17))
    f = fade(0.17, fp)
    k = 0.5 + 0.5 * math.exp(0.3 * fbm2(x, v, fs * 13 + bi, 0.3, fp, 0.004, 0.8))
    ir = mix(0.12, 0.04 + 0.3 * hashf(ci, row, fs, 117), f) * k
    ig = mix(0.11, 0.04 + 0.25 * hashf(ci, row, fs, 118), f) * k
    ib = mix(0.1, 0.04 + 0.25 * hashf(ci, row, fs, 119), f) * k
    return True, mix(ir, 0.3, shelf), mix(ig, 0.3, shelf), mix(ib, 0.29, shelf)


@njit(cache=True)
def facade_wall(u, z, r, g, b, fp, par, fs):
    """The wall material of a facade at (u, z) over its base colour (r, g, b): brick in running bond
    (style 1), concrete panels (style 2), else plain render."""
    style = np.int64(par[P_STYLE])
    if style == 1:  # brick, running bond
        course = 0.075
        blen = 0.25
        row = np.int64(math.floor(z / course))
        off = 0.5 * blen * (row & 1)
        bi = np.int64(math.floor((u + off) / blen))
        var = (hashf(bi, row, fs, 3) - 0.5) * 0.4 * fade(course, fp)
        r *= 1.0 + var
        g *= 1.0 + 0.9 * var
        b *= 1.0 + 0.8 * var
        cov = 1.0 - (1.0 - lines(z, course, 0.012, fp)) * (1.0 - lines(u + off, blen, 0.012, fp))
        r = mix(r, 0.42, cov)
        g = mix(g, 0.4, cov)
        b = mix(b, 0.37, cov)
    elif style == 2:  # concrete panels
        pw = 1.5
        ph = par[P_FLOOR]
        pi = np.int64(math.floor(u / pw))
        pj = np.int64(math.floor((z - par[P_Z0]) / ph))
        var = (hashf(pi, pj, fs, 4) - 0.5) * 0.2 * fade(pw, fp)
        r *= 1.0 + var
        g *= 1.0 + var
        b *= 1.0 + var
        cov = 1.0 - (1.0 - lines(u, pw, 0.02, fp)) * (1.0 - lines(z - par[P_Z0], ph, 0.02, fp))
        k = 1.0 - 0.6 * cov
        r *= k
        g *= k
        b *= k
    return r, g, b


@njit(cache=True)
def ground_floor_opening(ub, v, bi, n, bay, hg, fp, par, fs):
    """(hit, r, g, b) of the ground floor's opening of bay bi at (ub, v): a shopfront, the door or a
    window."""
    if hashf(bi, 0, fs, 9) < par[P_SHOP]:
        return shopfront(ub, v, bay, hg, fp, fs, bi)
    if bi == np.int64(par[P_DOOR] * n):
        if abs(ub) < 0.65 and v < 2.4:
            if abs(ub) > 0.57 or v > 2.32:
                return True, par[P_FR], par[P_FG], par[P_FB]
            pan = 1.0 - 0.4 * max(lines(ub, 0.4, 0.03, fp), lines(v, 0.55, 0.03, fp))
            dr = 0.12 + 0.2 * hashf(fs, 0, 0, 7)
            return True, dr * pan, 0.6 * dr * pan, 0.35 * dr * pan
        return False, 0.0, 0.0, 0.0
    wh = min(hg - 1.9, 1.7)
    return window(
        ub, v - 1.1, 0.5 * bay * par[P_WINW], wh, fp, fs, bi, np.int64(-1), par[P_FR], par[P_FG], par[P_FB]
    )


@njit(cache=True)
def facade_openings(u, z, L, ztop, r, g, b, fp, par, fs):
    """Windows, doors and shopfronts in the facade's bays over the wall colour (r, g, b)."""
    hg = par[P_GFLOOR]
    hf = par[P_FLOOR]
    bay = par[P_BAY]
    v = z - par[P_Z0]
    htop = ztop - par[P_Z0]
    n = max(1, np.int64(L / bay))
    m = 0.5 * (L - n * bay)
    bi = np.int64(math.floor((u - m) / bay))
    ub = u - m - (bi + 0.5) * bay
    if not 0 <= bi < n:
        return r, g, b
    if hg > 0.0 and v < hg:
        hit, wr, wg, wb = ground_floor_opening(ub, v, bi, n, bay, hg, fp, par, fs)
        if hit:
            return wr, wg, wb
        return r, g, b
    fl = np.int64(math.floor((v - hg) / hf))
    if hg + (fl + 1) * hf <= htop - par[P_PARAPET] + 1e-6:
        vf = v - hg - fl * hf
        hit, wr, wg, wb = window(
            ub, vf - 0.85, 0.5 * bay * par[P_WINW], hf * par[P_WINH], fp, fs, bi, fl, par[P_FR], par[P_FG],
            par[P_FB],
        )  # fmt: skip
        if hit:
            return wr, wg, wb
    return r, g, b


@njit(cache=True)
def facade(u, z, L, ztop, fp, par, fs, atlas, aoff, adim, lut):
    """Albedo of a building facade at (u, z): u metres along the face from its left end (seen from
    outside), z height; L face length, ztop the top of the box."""
    r = par[P_R]
    g = par[P_G]
    b = par[P_B]
    # weathering: low-frequency stains and tint
    st = fbm2(u, z, fs * 3 + 1, 9.0, fp, 0.5, 0.6)
    r *= math.exp(0.35 * st)
    g *= math.exp(0.33 * st)
    b *= math.exp(0.3 * st + 0.1 * fbm2(u, z, fs * 3 + 2, 6.0, fp, 1.0, 0.5))
    if par[P_PHOTO] > 0.0:
        r, g, b = facade_photo(u, z, fp, par[P_PHOTO], fs, atlas, aoff, adim, lut)
        k = math.exp(0.12 * fbm2(u, z, fs * 5 + 7, 0.25, fp, 0.002, 0.85))
        return r * k, g * k, b * k
    if par[P_WALL] >= 0.0:
        r, g, b = wall_photo(u, z, fp, par, atlas, aoff, adim, lut)
    else:
        r, g, b = facade_wall(u, z, r, g, b, fp, par, fs)
    r, g, b = facade_openings(u, z, L, ztop, r, g, b, fp, par, fs)
    hg = par[P_GFLOOR]
    v = z - par[P_Z0]
    htop = ztop - par[P_Z0]
    # cornice above the ground floor, plinth, coping
    if hg > 0.0:
        c = band(v, hg - 0.05, hg + 0.15, fp)
        r, g, b = mix(r, 0.6, c), mix(g, 0.58, c), mix(b, 0.54, c)
        p = band(v, -1.0, 0.4, fp)
        r, g, b = mix(r, 0.2, p), mix(g, 0.19, p), mix(b, 0.18, p)
    c = band(v, htop - 0.12, htop + 1.0, fp)
    r, g, b = mix(r, 0.45, c), mix(g, 0.45, c), mix(b, 0.44, c)
    k = math.exp(0.3 * fbm2(u, z, fs * 5 + 7, 1.0, fp, 0.05, 0.85))
    k *= math.exp(0.6 * fbm2(u, z, fs * 5 + 10, 0.04, fp, 0.002, 0.95))  # grain of the surface
    k *= 1.0 - 0.45 * spots(u, z, 0.2, 0.35, 0.006, 0.03, fp, fs * 5 + 8)  # dirt
    k *= 1.0 + 0.35 * spots(u + 0.1, z, 0.3, 0.25, 0.01, 0.04, fp, fs * 5 + 9)  # chipped paint
    return r * k, g * k, b * k


@njit(cache=True)
def roof(x, y, bx, fp, par, fs):
    """Albedo of a flat building roof at (x, y); bx the box (lo xyz, hi xyz)."""
    e = min(x - bx[0], bx[3] - x, y - bx[1], bx[4] - y)
    if e < 0.3:  # coping with joints
        j = lines(x + y, 1.0, 0.012, fp)
        k = 1.0 - 0.5 * j
        kn = math.exp(0.2 * fbm2(x, y, fs * 3 + 5, 0.5, fp, 0.003, 0.85))
        return 0.5 * k * kn, 0.49 * k * kn, 0.46 * k * kn
    rt = np.int64(par[P_ROOF])
    r = par[P_R2]
    g = par[P_G2]
    b = par[P_B2]
    stain = fbm2(x, y, fs * 3 + 6, 8.0, fp, 0.5, 0.6)
    k = math.exp(0.3 * stain)
    if rt == 0:  # gravel
        k *= math.exp(0.35 * fbm2(x, y, fs * 3 + 7, 0.4, fp, 0.003, 0.92))
    elif rt == 1:  # bitumen membrane with lighter seams
        seam = lines(y, 1.0, 0.05, fp)
        r, g, b = mix(r, r * 1.8, seam), mix(g, g * 1.8, seam), mix(b, b * 1.8, seam)
        k *= math.exp(0.2 * fbm2(x, y, fs * 3 + 8, 1.0, fp, 0.003, 0.85))
    elif rt == 2:  # green roof (sedum)
        n2 = fbm2(x, y, fs * 3 + 9, 2.0, fp, 0.005, 0.85)
        r *= math.exp(0.6 * n2)
        k *= math.exp(0.3 * fbm2(x, y, fs * 3 + 10, 0.3, fp, 0.003, 0.9))
    else:  # metal sheet with standing seams
        seam = lines(x, 0.6, 0.04, fp)
        k *= (1.0 + 0.5 * seam) * math.exp(0.12 * fbm2(x, y, fs * 3 + 11, 1.0, fp, 0.003, 0.85))
    # skylights
    ci = np.int64(math.floor(x / 7.0))
    cj = np.int64(math.floor(y / 7.0))
    if hashf(ci, cj, fs, 121) < 0.25:
        sx = ci * 7.0 + 1.5 + 4.0 * hashf(ci, cj, fs, 122)
        sy = cj * 7.0 + 1.5 + 4.0 * hashf(ci, cj, fs, 123)
        if abs(x - sx) < 0.6 and abs(y - sy) < 0.9 and x - bx[0] > 0.8 and bx[3] - x > 0.8:
            if y - bx[1] > 0.8 and bx[4] - y > 0.8:
                if abs(x - sx) > 0.52 or abs(y - sy) > 0.82:
                    return 0.5, 0.5, 0.5
                return 0.05, 0.07, 0.1 + 0.05 * hashf(ci, cj, fs, 124)
    return r * k, g * k, b * k


@njit(cache=True)
def roofbox_albedo(face, u, L, px, py, pz, bx, par, fp, fs):
    """A box on a roof: a stair house with a door (style > 0.5) or metal cladding with a louvre."""
    r = par[P_R]
    g = par[P_G]
    b = par[P_B]
    if face >= 4:
        k = math.exp(0.25 * fbm2(px, py, fs, 1.0, fp, 0.003, 0.85))
        return 0.9 * r * k, 0.9 * g * k, 0.9 * b * k
    v = pz - bx[2]
    if par[P_STYLE] > 0.5:  # stair house with a door
        if abs(u - 0.5 * L) < 0.5 and v < 2.1 and face == np.int64(par[P_AXIS]):
            return 0.15, 0.2, 0.28
    else:  # metal cladding with ribs and a louvre panel
        k = 1.0 - 0.3 * lines(u, 0.12, 0.02, fp)
        if abs(u - 0.5 * L) < 0.35 * L and abs(v - 0.5 * (bx[5] - bx[2])) < 0.25:
            k *= 1.0 - 0.6 * lines(v, 0.05, 0.02, fp)
        r, g, b = r * k, g * k, b * k
    k = math.exp(0.18 * fbm2(u, pz, fs, 1.0, fp, 0.003, 0.85))
    return r * k, g * k, b * k


@njit(cache=True)
def car_albedo(face, u, L, px, py, pz, bx, par, fp, fs):
    """A car's body (wheels, lights, number plate) or, style > 0.5, its cabin (glass and pillars)."""
    r = par[P_R]
    g = par[P_G]
    b = par[P_B]
    v = pz - bx[2]
    if par[P_STYLE] > 0.5:  # cabin: glass all around, pillars, roof in paint colour
        if face >= 4:
            return r, g, b
        k = 0.6 * L
        if abs(u - 0.5 * L) > k * 0.98 or v < 0.05:
            return r * 0.8, g * 0.8, b * 0.8
        return par[P_R2], par[P_G2], par[P_B2] + 0.03 * v
    if face >= 4:
        k = math.exp(0.05 * fbm2(px, py, fs, 1.0, fp, 0.005, 0.8))
        return r * k, g * k, b * k
    side = (face // 2) != np.int64(par[P_AXIS])
    if side:  # wheels
        for wx in (0.8, L - 0.8):
            d = math.hypot(u - wx, v - 0.33)
            if d < 0.33:
                return (0.3, 0.3, 0.32) if d < 0.18 else (0.03, 0.03, 0.03)
        if v < 0.25:
            return 0.04, 0.04, 0.04
        if abs(v - 0.75) < 0.01 + 0.5 * fp:
            return r * 0.5, g * 0.5, b * 0.5
    else:  # lights and number plate
        if abs(u - 0.5 * L) < 0.26 and abs(v - 0.45) < 0.06:
            return 0.8, 0.8, 0.75
        if abs(abs(u - 0.5 * L) - 0.6) < 0.15 and abs(v - 0.75) < 0.07:
            lr = 0.7 if (face & 1) == 0 else 0.8
            return lr, 0.1 if (face & 1) == 0 else 0.75, 0.1 if (face & 1) == 0 else 0.7
        if v < 0.3:
            return 0.05, 0.05, 0.05
    k = math.exp(0.04 * fbm2(u, pz, fs, 1.0, fp, 0.005, 0.8))
    return r * k, g * k, b * k


@njit(cache=True)
def kiosk_albedo(face, u, L, pz, bx, par, fp, fs):
    """A kiosk: striped walls, a light sign band at the top, a dark hatch on one side."""
    v = pz - bx[2]
    if face >= 4:
        return 0.3, 0.3, 0.3
    top = bx[5] - bx[2]
    if v > top - 0.5:
        return 0.8, 0.78, 0.7
    if face & 1 == 1 and abs(u - 0.5 * L) < 0.6 and 1.0 < v < 1.9:
        return 0.08, 0.09, 0.1
    stripe = lines(u, 0.5, 0.25, fp)
    k = math.exp(0.12 * fbm2(u, pz, fs, 1.0, fp, 0.003, 0.85))
    return mix(par[P_R], 0.85, stripe) * k, mix(par[P_G], 0.85, stripe) * k, mix(par[P_B], 0.8, stripe) * k


@njit(cache=True)
def box_albedo(mat, face, px, py, pz, bx, par, fp, atlas, aoff, adim, lut):
    """Albedo of box primitive `bx` (lo xyz, hi xyz) of material mat at a point on face
    (0 -x, 1 +x, 2 -y, 3 +y, 4 -z, 5 +z)."""
    seed = np.int64(par[P_SEED])
    fs = seed * 8 + face
    if face == 0:
        u = bx[4] - py
        L = bx[4] - bx[1]
    elif face == 1:
        u = py - bx[1]
        L = bx[4] - bx[1]
    elif face == 2:
        u = px - bx[0]
        L = bx[3] - bx[0]
    else:
        u = bx[3] - px
        L = bx[3] - bx[0]
    if mat == MAT_BUILDING:
        if face >= 4:
            return roof(px, py, bx, fp, par, fs)
        return facade(u, pz, L, bx[5], fp, par, fs, atlas, aoff, adim, lut)
    if mat == MAT_ROOFBOX:
        return roofbox_albedo(face, u, L, px, py, pz, bx, par, fp, fs)
    if mat == MAT_CAR:
        return car_albedo(face, u, L, px, py, pz, bx, par, fp, fs)
    if mat == MAT_KIOSK:
        return kiosk_albedo(face, u, L, pz, bx, par, fp, fs)
    if mat == MAT_KERB:
        j = lines(px + py, 1.0, 0.01, fp)
        k = (1.0 - 0.5 * j) * math.exp(0.25 * fbm2(px + py, pz + face, fs, 0.5, fp, 0.002, 0.88))
        return 0.45 * k, 0.44 * k, 0.42 * k
    if mat == MAT_TRUNK:
        k = math.exp(0.5 * fbm2(u * 3.0, pz, fs, 0.6, fp, 0.004, 0.85))
        return 0.12 * k, 0.09 * k, 0.06 * k
    k = 1.0
    if mat == MAT_POLE:
        k = math.exp(0.1 * fbm2(u, pz, fs, 0.5, fp, 0.003, 0.8))
    return par[P_R] * k, par[P_G] * k, par[P_B] * k


@njit(cache=True)
def paved_albedo(zt, x, y, fp, s):
    """Grass or field (zone Z_FIELD, Z_GRASS), sidewalk tiles, cobblestones in offset rows, or what
    lies under a building."""
    if zt == Z_FIELD or zt == Z_GRASS:
        n1 = fbm2(x, y, s + 1, 16.0, fp, 0.5, 0.7)
        n2 = fbm2(x, y, s + 2, 0.5, fp, 0.002, 0.92)
        dry = 0.5 + 0.5 * fbm2(x, y, s + 3, 6.0, fp, 0.5, 0.6)
        r = (0.09 + 0.08 * dry) * math.exp(0.5 * n1 + 0.5 * n2)
        g = (0.17 + 0.03 * dry) * math.exp(0.4 * n1 + 0.45 * n2)
        b = 0.04 * math.exp(0.3 * n1 + 0.4 * n2)
        return r, g, b
    if zt == Z_SIDEWALK:
        t = 0.4
        ti = np.int64(math.floor(x / t))
        tj = np.int64(math.floor(y / t))
        var = (hashf(ti, tj, s, 5) - 0.5) * 0.3 * fade(t, fp)
        grout = 1.0 - (1.0 - lines(x, t, 0.008, fp)) * (1.0 - lines(y, t, 0.008, fp))
        k = (1.0 + var) * (1.0 - 0.5 * grout)
        k *= math.exp(0.3 * fbm2(x, y, s + 6, 4.0, fp, 0.002, 0.88))
        k *= 1.0 - 0.55 * spots(x, y, 0.25, 0.3, 0.008, 0.025, fp, s + 20)  # chewing gum, stains
        return 0.36 * k, 0.34 * k, 0.32 * k
    if zt == Z_PAVED:  # cobblestones in offset rows
        t = 0.14
        tj = np.int64(math.floor(y / t))
        off = 0.5 * t * (tj & 1)
        ti = np.int64(math.floor((x + off) / t))
        f = fade(t, fp)
        var = (hashf(ti, tj, s, 7) - 0.5) * 0.6 * f
        tint = (hashf(ti, tj, s, 8) - 0.5) * 0.2 * f
        joint = 1.0 - (1.0 - lines(y, t, 0.02, fp)) * (1.0 - lines(x + off, t, 0.02, fp))
        k = (1.0 + var) * (1.0 - 0.55 * joint)
        k *= math.exp(0.2 * fbm2(x, y, s + 9, 2.0, fp, 0.002, 0.85))
        return 0.3 * k * (1 + tint), 0.28 * k, 0.26 * k * (1 - tint)
    return 0.25, 0.24, 0.22  # under buildings


@njit(cache=True)
def road_marks(x, y, fp, lay, s, r, g, b):
    """Road markings (centre and parking-lane lines, zebra crossings), manholes and drains over the
    asphalt colour (r, g, b) of a road at (x, y); lay: X0, Y0, Px, Py, road width, blocks x, y."""
    lx = x - lay[0]
    ly = y - lay[1]
    rw = lay[4]
    ix = np.int64(math.floor(lx / lay[2]))
    iy = np.int64(math.floor(ly / lay[3]))
    rx = lx - ix * lay[2]
    ry = ly - iy * lay[3]
    in_x = rx < rw  # on a north-south road (across = rx)
    in_y = ry < rw  # on an east-west road (across = ry)
    if in_x and in_y:  # intersection
        return r, g, b
    if in_x:
        across = rx
        along = ry - rw
        seg = lay[3] - rw
        ri = ix * 1000 + iy
        salong = ly
    elif in_y:
        across = ry
        along = rx - rw
        seg = lay[2] - rw
        ri = iy * 1000 + ix + 500000
        salong = lx
    else:
        return r, g, b
    m = 0.0
    # dashed centre line
    m = max(m, band(across, 0.5 * rw - 0.06, 0.5 * rw + 0.06, fp) * lines(along - 1.5, 6.0, 3.0, fp))
    # edge lines of the parking lanes
    m = max(m, band(across, 2.2, 2.3, fp) + band(across, rw - 2.3, rw - 2.2, fp))
    # zebra crossings next to intersections
    for e in range(2):
        if hashf(ri, e, s, 13) < 0.6:
            d = along - 1.0 if e == 0 else seg - 1.0 - along
            if 0.0 <= d <= 3.0 and 2.4 < across < rw - 2.4:
                m = max(m, lines(across, 1.0, 0.5, fp) * band(d, 0.0, 3.0, fp))
    if m > 0.0:
        wk = math.exp(0.2 * fbm2(x, y, s + 14, 0.3, fp, 0.002, 0.9))
        r, g, b = mix(r, 0.7 * wk, m), mix(g, 0.7 * wk, m), mix(b, 0.68 * wk, m)
    return road_fixtures(salong, across, ri, rw, fp, s, r, g, b)


@njit(cache=True)
def road_fixtures(salong, across, ri, rw, fp, s, r, g, b):
    """Manholes every ~16 m and drains at the kerb of road ri, at (salong, across) metres along and
    across it; else (r, g, b)."""
    c = np.int64(math.floor(salong / 16.0))
    if hashf(ri, c, s, 15) < 0.6:
        ca = c * 16.0 + 3.0 + 10.0 * hashf(ri, c, s, 16)
        cc = 3.0 + (rw - 6.0) * hashf(ri, c, s, 17)
        da = salong - ca
        dc = across - cc
        d = math.hypot(da, dc)
        if d < 0.34:
            if d > 0.3:
                return 0.25, 0.25, 0.24
            grid = max(lines(da + dc, 0.06, 0.015, fp), lines(da - dc, 0.06, 0.015, fp))
            k = (1.0 + 0.6 * grid) * math.exp(0.25 * fbm2(da, dc, s + ri, 0.2, fp, 0.002, 0.8))
            return 0.07 * k, 0.065 * k, 0.06 * k
    c = np.int64(math.floor(salong / 22.0))
    da = salong - (c * 22.0 + 11.0)
    for side in range(2):
        dc = across - (0.35 if side == 0 else rw - 0.35)
        if abs(da) < 0.3 and abs(dc) < 0.2 and hashf(ri, c * 2 + side, s, 18) < 0.7:
            slot = lines(da, 0.06, 0.025, fp)
            k = 1.0 - 0.8 * slot
            return 0.12 * k, 0.12 * k, 0.12 * k
    return r, g, b


@njit(cache=True)
def ground_albedo(x, y, fp, zone, zmeta, lay, seed):
    """Albedo of the ground plane at (x, y): zone raster lookup + road markings, manholes, drains."""
    zi = np.int64(math.floor((x - zmeta[0]) / zmeta[2]))
    zj = np.int64(math.floor((y - zmeta[1]) / zmeta[2]))
    zt = Z_FIELD
    if 0 <= zi < zone.shape[1] and 0 <= zj < zone.shape[0]:
        zt = zone[zj, zi]
    s = seed * 16
    if zt != Z_ROAD and zt != Z_PARKING:
        return paved_albedo(zt, x, y, fp, s)
    # asphalt
    ag = 0.11 if zt == Z_ROAD else 0.14
    k = math.exp(0.25 * fbm2(x, y, s + 10, 8.0, fp, 0.5, 0.6))
    k *= math.exp(0.3 * fbm2(x, y, s + 11, 0.5, fp, 0.06, 0.8))
    k *= math.exp(0.55 * fbm2(x, y, s + 19, 0.06, fp, 0.002, 0.95))  # aggregate grain
    k *= 1.0 + 0.8 * spots(x, y, 0.15, 0.3, 0.004, 0.015, fp, s + 21)  # light stones
    k *= 1.0 - 0.5 * spots(x, y, 0.9, 0.2, 0.03, 0.12, fp, s + 22)  # oil and tar spots
    r = ag * k
    g = ag * k
    b = ag * k * 1.05
    if zt == Z_PARKING:
        oil = fbm2(x, y, s + 12, 3.0, fp, 0.1, 0.7)
        if oil > 0.3:
            r, g, b = r * 0.6, g * 0.6, b * 0.6
        return r, g, b
    return road_marks(x, y, fp, lay, s, r, g, b)


# ------------------------------------------------------------------------------ ray casting


@njit(cache=True)
def ray_box(ox, oy, oz, ix, iy, iz, boxes, i):
    """Entry distance and face of the ray o + t d into box i, or (inf, -1); ix, iy, iz = 1 / d
    (+-inf for a zero component)."""
    ta = (boxes[i, 0] - ox) * ix
    tb = (boxes[i, 3] - ox) * ix
    if ta < tb:
        tn, tf, f = ta, tb, 0
    else:
        tn, tf, f = tb, ta, 1
    ta = (boxes[i, 1] - oy) * iy
    tb = (boxes[i, 4] - oy) * iy
    if ta > tb:
        ta, tb = tb, ta
        fa = 3
    else:
        fa = 2
    if ta > tn:
        tn, f = ta, fa
    tf = min(tf, tb)
    ta = (boxes[i, 2] - oz) * iz
    tb = (boxes[i, 5] - oz) * iz
    if ta > tb:
        ta, tb = tb, ta
        fa = 5
    else:
        fa = 4
    if ta > tn:
        tn, f = ta, fa
    tf = min(tf, tb)
    if not (tn <= tf) or tn <= _EPS:  # also rejects NaN (0 * inf on a slab boundary)
        return _INF, -1
    return tn, f


@njit(cache=True)
def ray_sphere(ox, oy, oz, dx, dy, dz, sph, i):
    """Entry distance of the ray into sphere i (x, y, z, r), or inf."""
    lx = ox - sph[i, 0]
    ly = oy - sph[i, 1]
    lz = oz - sph[i, 2]
    a = dx * dx + dy * dy + dz * dz
    bq = lx * dx + ly * dy + lz * dz
    c = lx * lx + ly * ly + lz * lz - sph[i, 3] * sph[i, 3]
    disc = bq * bq - a * c
    if disc < 0.0 or c < 0.0:
        return _INF
    t = (-bq - math.sqrt(disc)) / a
    return t if t > _EPS else _INF


@njit(cache=True)
def clip_to_grid(ox, oy, oz, dx, dy, dz, gmeta, t_max):
    """(t0, t1): the part of the ray o + t d, eps < t < t_max, inside the slab 0 <= z <= zmax over the
    grid's rectangle (gmeta: x0, y0, cell, nx, ny, zmax); t0 >= t1 when it misses."""
    gx0 = gmeta[0]
    gy0 = gmeta[1]
    cs = gmeta[2]
    nx = np.int64(gmeta[3])
    ny = np.int64(gmeta[4])
    zmax = gmeta[5]
    t0 = _EPS
    t1 = t_max
    for a in range(3):
        o = ox if a == 0 else (oy if a == 1 else oz)
        d = dx if a == 0 else (dy if a == 1 else dz)
        lo = gx0 if a == 0 else (gy0 if a == 1 else 0.0)
        hi = gx0 + nx * cs if a == 0 else (gy0 + ny * cs if a == 1 else zmax)
        if d != 0.0:
            ta = (lo - o) / d
            tb = (hi - o) / d
            if ta > tb:
                ta, tb = tb, ta
            t0 = max(t0, ta)
            t1 = min(t1, tb)
        elif o < lo or o > hi:
            return _INF, 0.0
    return t0, t1


@njit(cache=True)
def dda_axis(o, d, g0, cs, c):
    """(step, t of the next cell boundary, t per cell) along one axis of the 2-D DDA, from cell c."""
    if d > 0.0:
        return 1, (g0 + (c + 1) * cs - o) / d, cs / d
    if d < 0.0:
        return -1, (g0 + c * cs - o) / d, -cs / d
    return 0, _INF, _INF


@njit(cache=True)
def trace(ox, oy, oz, dx, dy, dz, boxes, sph, gmeta, cstart, citems, any_hit, skip):
    """Nearest hit along o + t d: (t, kind, index, face); kind 0 none, 1 ground, 2 box, 3 sphere.

    Walks the uniform xy grid (gmeta: x0, y0, cell, nx, ny, zmax, then the top of each cell's content)
    cell by cell (2-D DDA), skipping cells whose content lies below the ray. With any_hit = 1, returns
    at the first object hit (shadow rays; the ground is ignored). Grid item `skip` (box i: i, sphere j:
    N + j; -1: none) is ignored (a tree crown does not shadow itself). Constant arguments are passed as
    np.int64(...) throughout this module: a literal would make numba compile a specialisation per value.
    """
    best = _INF
    kind = 0
    idx = -1
    face = -1
    if dz < 0.0 and any_hit == 0:
        best = -oz / dz
        kind = 1
    nb = boxes.shape[0]
    gx0 = gmeta[0]
    gy0 = gmeta[1]
    cs = gmeta[2]
    nx = np.int64(gmeta[3])
    ny = np.int64(gmeta[4])
    t0, t1 = clip_to_grid(ox, oy, oz, dx, dy, dz, gmeta, best)
    if t0 >= t1:
        return best, kind, idx, face
    ix = 1.0 / dx if dx != 0.0 else _INF
    iy = 1.0 / dy if dy != 0.0 else _INF
    iz = 1.0 / dz if dz != 0.0 else _INF
    ci = min(max(np.int64((ox + t0 * dx - gx0) / cs), 0), nx - 1)
    cj = min(max(np.int64((oy + t0 * dy - gy0) / cs), 0), ny - 1)
    sx, tmx, tdx = dda_axis(ox, dx, gx0, cs, ci)
    sy, tmy, tdy = dda_axis(oy, dy, gy0, cs, cj)
    tin = t0
    while True:
        c = cj * nx + ci
        tnext = min(tmx, tmy)
        zlo = oz + dz * (min(tnext, t1) if dz < 0.0 else tin)
        if zlo <= gmeta[6 + c]:
            for k in range(cstart[c], cstart[c + 1]):
                it = citems[k]
                if it == skip:
                    continue
                if it < nb:
                    t, f = ray_box(ox, oy, oz, ix, iy, iz, boxes, it)
                    if t < best:
                        best = t
                        kind = 2
                        idx = it
                        face = f
                        if any_hit != 0:
                            return best, kind, idx, face
                else:
                    t = ray_sphere(ox, oy, oz, dx, dy, dz, sph, it - nb)
                    if t < best:
                        best = t
                        kind = 3
                        idx = it - nb
                        face = 0
                        if any_hit != 0:
                            return best, kind, idx, face
        if best <= tnext or tnext >= t1:
            break
        tin = tnext
        if tmx < tmy:
            ci += sx
            tmx += tdx
            if ci < 0 or ci >= nx:
                break
        else:
            cj += sy
            tmy += tdy
            if cj < 0 or cj >= ny:
                break
    return best, kind, idx, face


# ------------------------------------------------------------------------------------ relief
@njit(cache=True)
def face_frame(face, bx):
    """u = ua x + ub y + uc along a vertical box face (0 -x, 1 +x, 2 -y, 3 +y; u as box_albedo's),
    its outward normal (nx, ny) and length L: (ua, ub, uc, nx, ny, L)."""
    if face == 0:
        return 0.0, -1.0, bx[4], -1.0, 0.0, bx[4] - bx[1]
    if face == 1:
        return 0.0, 1.0, -bx[1], 1.0, 0.0, bx[4] - bx[1]
    if face == 2:
        return 1.0, 0.0, -bx[0], 0.0, -1.0, bx[3] - bx[0]
    return -1.0, 0.0, bx[3], 0.0, 1.0, bx[3] - bx[0]


@njit(cache=True)
def opening_rect(u, z, L, ztop, par, fs):
    """The opening of a facade around (u, z) (facade_openings' layout: a window's frame and glass, a door,
    a shop window): (inside, u0, u1, z0, z1), the rectangle in face coordinates."""
    hg = par[P_GFLOOR]
    bay = par[P_BAY]
    v = z - par[P_Z0]
    n = max(1, np.int64(L / bay))
    m = 0.5 * (L - n * bay)
    bi = np.int64(math.floor((u - m) / bay))
    if not 0 <= bi < n:
        return False, 0.0, 0.0, 0.0, 0.0
    uc = m + (bi + 0.5) * bay
    ww = 0.5 * bay * par[P_WINW]
    if hg > 0.0 and v < hg:
        if hashf(bi, 0, fs, 9) < par[P_SHOP]:  # the shop window under its sign band
            hw, v0, v1 = 0.5 * bay - 0.14, 0.51, hg - 0.96
        elif bi == np.int64(par[P_DOOR] * n):
            hw, v0, v1 = 0.57, 0.0, 2.32
        else:
            hw, v0, v1 = ww, 1.1, 1.1 + min(hg - 1.9, 1.7)
    else:
        hf = par[P_FLOOR]
        fl = np.int64(math.floor((v - hg) / hf))
        if hg + (fl + 1) * hf > ztop - par[P_Z0] - par[P_PARAPET] + 1e-6:
            return False, 0.0, 0.0, 0.0, 0.0
        hw, v0 = ww, hg + fl * hf + 0.85
        v1 = v0 + hf * par[P_WINH]
    z0 = par[P_Z0] + v0
    z1 = par[P_Z0] + v1
    inside = abs(u - uc) < hw and z0 < z < z1
    return inside, uc - hw, uc + hw, z0, z1


@njit(cache=True)
def relief(ox, oy, oz, dx, dy, dz, t, face, bx, par):
    """A camera ray that hit facade `face` of building box bx at t, through the recessed opening there
    (par[P_RELIEF] deep): (t, code, nface) with code 0 the wall (no opening: t unchanged), 1 the window
    or door at the back of the recess, 2 a reveal (jamb, sill or head) with normal nface."""
    fs = np.int64(par[P_SEED]) * 8 + face
    ua, ub, uc, nx, ny, L = face_frame(face, bx)
    px = ox + t * dx
    py = oy + t * dy
    pz = oz + t * dz
    u = ua * px + ub * py + uc
    inside, u0, u1, z0, z1 = opening_rect(u, pz, L, bx[5], par, fs)
    dn = -(nx * dx + ny * dy)
    if not inside or dn <= 0.0:
        return t, 0, face
    du = ua * dx + ub * dy
    tb = t + par[P_RELIEF] / dn
    tu = _INF
    if du > 0.0:
        tu = t + (u1 - u) / du
    elif du < 0.0:
        tu = t + (u0 - u) / du
    tz = _INF
    if dz > 0.0:
        tz = t + (z1 - pz) / dz
    elif dz < 0.0:
        tz = t + (z0 - pz) / dz
    if tb <= min(tu, tz):
        return tb, 1, face
    if tu < tz:  # a jamb, facing against the ray's travel along u
        wx = -ua if du > 0.0 else ua
        wy = -ub if du > 0.0 else ub
        if wx != 0.0:
            return tu, 2, (0 if wx < 0.0 else 1)
        return tu, 2, (2 if wy < 0.0 else 3)
    return tz, 2, (4 if dz > 0.0 else 5)  # the head's soffit (seen from below) or the sill


@njit(cache=True)
def out_of_recess(px, py, pz, face, bx, par, sx, sy, sz):
    """Whether the ray from a point in a recessed opening of facade `face` towards s leaves the recess
    through the opening rather than through a reveal (the reveals' shadows on the glass and on each
    other)."""
    fs = np.int64(par[P_SEED]) * 8 + face
    ua, ub, uc, nx, ny, L = face_frame(face, bx)
    sn = nx * sx + ny * sy
    if sn <= 0.0:
        return False
    if face < 2:
        depth = nx * (bx[0] if face == 0 else bx[3]) - nx * px
    else:
        depth = ny * (bx[1] if face == 2 else bx[4]) - ny * py
    inside, u0, u1, z0, z1 = opening_rect(ua * px + ub * py + uc, pz, L, bx[5], par, fs)
    if not inside:
        return True
    tout = max(depth, 0.0) / sn
    u = ua * (px + sx * tout) + ub * (py + sy * tout) + uc
    z = pz + sz * tout
    return u0 <= u <= u1 and z0 <= z <= z1


@njit(cache=True)
def reveal_albedo(pz, px, py, fp, par, atlas, aoff, adim, lut):
    """A reveal of a recessed opening: the wall's photo, else its render in its colour, a little darker
    and stained."""
    if par[P_WALL] >= 0.0:
        return wall_photo(px + py, pz, fp, par, atlas, aoff, adim, lut)
    fs = np.int64(par[P_SEED]) * 8 + 7
    k = 0.9 * math.exp(0.25 * fbm2(px + py, pz, fs, 0.3, fp, 0.003, 0.85))
    return par[P_R] * k, par[P_G] * k, par[P_B] * k


@njit(cache=True)
def trace_camera(ox, oy, oz, dx, dy, dz, boxes, bmat, bpar, sph, gmeta, cstart, citems):
    """trace() of a camera ray, into the recessed openings of facades with relief: (t, kind, idx, face,
    code, nface) with code and nface as relief() gives them (code 0, nface = face elsewhere)."""
    t, kind, idx, face = trace(
        ox, oy, oz, dx, dy, dz, boxes, sph, gmeta, cstart, citems, np.int64(0), np.int64(-1)
    )
    if kind == 2 and face < 4 and bmat[idx] == MAT_BUILDING and bpar[idx, P_RELIEF] > 0.0:
        if bpar[idx, P_PHOTO] <= 0.0:
            t, code, nface = relief(ox, oy, oz, dx, dy, dz, t, face, boxes[idx], bpar[idx])
            return t, kind, idx, face, code, nface
    return t, kind, idx, face, 0, face


@njit(cache=True)
def sky(dx, dy, dz, light, seed):
    """Sky radiance in direction d: horizon-zenith gradient, sun glow and soft clouds."""
    n = math.sqrt(dx * dx + dy * dy + dz * dz)
    ex = dx / n
    ey = dy / n
    ez = max(dz / n, 0.0)
    w = 1.0 - (1.0 - ez) ** 3
    r = mix(light[L_HOR], light[L_ZEN], w)
    g = mix(light[L_HOR + 1], light[L_ZEN + 1], w)
    b = mix(light[L_HOR + 2], light[L_ZEN + 2], w)
    c = max(ex * light[L_SUN] + ey * light[L_SUN + 1] + ez * light[L_SUN + 2], 0.0)
    glow = 0.25 * c**32 + 0.05 * c**4
    r += glow * light[L_SUNC]
    g += glow * light[L_SUNC + 1]
    b += glow * light[L_SUNC + 2]
    if light[L_CLOUD] > 0.0 and ez > 0.01:
        cx = ex / (ez + 0.08) * 1000.0
        cy = ey / (ez + 0.08) * 1000.0
        cn = fbm2(cx, cy, seed * 16 + 15, 1500.0, 20.0, 40.0, 0.55)
        cov = min(max((cn + 0.6 - light[L_CLOUD]) * 3.0, 0.0), 1.0) * light[L_CLOUD] * min(ez * 8.0, 1.0)
        kc = 0.9 + 0.3 * cn
        lum = 0.9 * (light[L_HOR] + light[L_HOR + 1] + light[L_HOR + 2]) / 3.0 + 0.1
        r = mix(r, lum * kc, cov)
        g = mix(g, lum * kc, cov)
        b = mix(b, lum * kc * 1.02, cov)
    return r, g, b


@njit(cache=True)
def surface_normal(kind, face, idx, px, py, pz, sph):
    """Unit normal of the hit: the ground (kind 1), box face `face` (kind 2), sphere idx (kind 3)."""
    if kind == 1:
        return 0.0, 0.0, 1.0
    if kind == 2:
        a = face // 2
        sgn = -1.0 if face % 2 == 0 else 1.0
        return (sgn if a == 0 else 0.0), (sgn if a == 1 else 0.0), (sgn if a == 2 else 0.0)
    rs = sph[idx, 3]
    return (px - sph[idx, 0]) / rs, (py - sph[idx, 1]) / rs, (pz - sph[idx, 2]) / rs


@njit(cache=True)
def foliage_albedo(px, py, pz, fp, par, bush):
    """A tree crown or bush at (px, py, pz): clumps of leaves with dark gaps between them."""
    fs = np.int64(par[P_SEED])
    n1 = fbm3(px, py, pz, fs, 1.6, fp, 0.3, 0.7)  # clumps of leaves
    n2 = fbm3(px, py, pz, fs + 1, 0.3, fp, 0.005, 0.85)  # leaves
    k = math.exp(0.5 * n1 + 0.6 * n2)
    gap = min(max((-n2 - 0.15) * 4.0, 0.0), 1.0) * fade(0.12, fp)  # holes between leaves: dark
    k *= 1.0 - 0.7 * gap
    dk = 0.7 if bush else 1.0
    return par[P_R] * k * dk * (1.0 + 0.25 * n1), par[P_G] * k * dk, par[P_B] * k * dk


@njit(cache=True)
def sunlit(px, py, pz, nx, ny, nz, t, skip, boxes, sph, gmeta, cstart, citems, light, recess, bpar):
    """n . sun at the hit, 0 where the sun is below its surface or something shadows it; recess: the
    facade (box * 8 + face) whose recessed opening holds the hit, -1 for none."""
    sx = light[L_SUN]
    sy = light[L_SUN + 1]
    sz = light[L_SUN + 2]
    ndl = nx * sx + ny * sy + nz * sz
    if ndl > 0.0 and light[L_SHADOW] > 0.0:
        e = 2e-3 + 1e-5 * t
        if recess >= 0:
            bi = recess // 8
            if not out_of_recess(
                px + nx * e, py + ny * e, pz + nz * e, recess % 8, boxes[bi], bpar[bi], sx, sy, sz
            ):
                return 0.0
        st = trace(
            px + nx * e, py + ny * e, pz + nz * e, sx, sy, sz, boxes, sph, gmeta, cstart, citems,
            np.int64(1), skip,
        )  # fmt: skip
        if st[1] != 0:
            ndl = 0.0
    return max(ndl, 0.0)


@njit(cache=True)
def radiance(
    ox, oy, oz, dx, dy, dz, f, boxes, bmat, bpar, sph, smat, spar, gmeta, cstart, citems,
    zone, zmeta, lay, atlas, aoff, adim, lut, light, seed,
):  # fmt: skip
    """Linear RGB radiance along a camera ray o + t d (d = R (x, y, 1), so t is the z-depth)."""
    t, kind, idx, face, code, nface = trace_camera(
        ox, oy, oz, dx, dy, dz, boxes, bmat, bpar, sph, gmeta, cstart, citems
    )
    if kind == 0:
        return sky(dx, dy, dz, light, seed)
    px = ox + t * dx
    py = oy + t * dy
    pz = 0.0 if kind == 1 else oz + t * dz
    dn = math.sqrt(dx * dx + dy * dy + dz * dz)
    nx, ny, nz = surface_normal(kind, nface, idx, px, py, pz, sph)
    cosi = abs(nx * dx + ny * dy + nz * dz) / dn
    fp = t / f / max(cosi, 0.05)
    if kind == 1:
        r, g, b = ground_albedo(px, py, fp, zone, zmeta, lay, seed)
    elif code == 2:
        r, g, b = reveal_albedo(pz, px, py, fp, bpar[idx], atlas, aoff, adim, lut)
    elif kind == 2:
        r, g, b = box_albedo(bmat[idx], face, px, py, pz, boxes[idx], bpar[idx], fp, atlas, aoff, adim, lut)
    else:
        r, g, b = foliage_albedo(px, py, pz, fp, spar[idx], smat[idx] == MAT_BUSH)
        # crowns are rough: soften the normal towards up
        nz = 0.6 * nz + 0.4
        nn = math.sqrt(nx * nx + ny * ny + nz * nz)
        nx, ny, nz = nx / nn, ny / nn, nz / nn
    skip = idx + boxes.shape[0] if kind == 3 else np.int64(-1)
    recess = idx * 8 + face if code != 0 else np.int64(-1)
    ndl = sunlit(px, py, pz, nx, ny, nz, t, skip, boxes, sph, gmeta, cstart, citems, light, recess, bpar)
    amb = 0.75 + 0.25 * nz
    lr = light[L_AMB] * amb + light[L_SUNC] * ndl
    lg = light[L_AMB + 1] * amb + light[L_SUNC + 1] * ndl
    lb = light[L_AMB + 2] * amb + light[L_SUNC + 2] * ndl
    r *= lr
    g *= lg
    b *= lb
    h = 1.0 - math.exp(-t * dn / light[L_HAZED])
    return mix(r, light[L_HAZEC], h), mix(g, light[L_HAZEC + 1], h), mix(b, light[L_HAZEC + 2], h)


@njit(parallel=True, cache=True)
def render(
    C, Rwc, fx, fy, cx, cy, ss, rows, boxes, bmat, bpar, sph, smat, spar, gmeta, cstart, citems,
    zone, zmeta, lay, atlas, aoff, adim, lut, light, seed, img, depth,
):  # fmt: skip
    """Render one pinhole image into img (H, W, 3) float32 linear RGB and depth (H, W) float32 z-depth.

    C (3,) camera centre, Rwc (3, 3) world_from_cam; pixel (row i, col j) samples COLMAP coordinates
    (j + (a + 0.5) / ss, i + (b + 0.5) / ss); its depth comes from the ray through (j + 0.5, i + 0.5).
    rows: a permutation of the rows (interleaved for load balance across threads).
    """
    H = img.shape[0]
    W = img.shape[1]
    inv = 1.0 / (ss * ss)
    for k in prange(H):
        i = rows[k]
        for j in range(W):
            ar = 0.0
            ag = 0.0
            ab = 0.0
            for sa in range(ss):
                for sb in range(ss):
                    xn = (j + (sa + 0.5) / ss - cx) / fx
                    yn = (i + (sb + 0.5) / ss - cy) / fy
                    dx = Rwc[0, 0] * xn + Rwc[0, 1] * yn + Rwc[0, 2]
                    dy = Rwc[1, 0] * xn + Rwc[1, 1] * yn + Rwc[1, 2]
                    dz = Rwc[2, 0] * xn + Rwc[2, 1] * yn + Rwc[2, 2]
                    r, g, b = radiance(
                        C[0], C[1], C[2], dx, dy, dz, fx, boxes, bmat, bpar, sph, smat, spar, gmeta,
                        cstart, citems, zone, zmeta, lay, atlas, aoff, adim, lut, light, seed,
                    )  # fmt: skip
                    ar += r
                    ag += g
                    ab += b
            img[i, j, 0] = ar * inv
            img[i, j, 1] = ag * inv
            img[i, j, 2] = ab * inv
            xn = (j + 0.5 - cx) / fx
            yn = (i + 0.5 - cy) / fy
            dx = Rwc[0, 0] * xn + Rwc[0, 1] * yn + Rwc[0, 2]
            dy = Rwc[1, 0] * xn + Rwc[1, 1] * yn + Rwc[1, 2]
            dz = Rwc[2, 0] * xn + Rwc[2, 1] * yn + Rwc[2, 2]
            t, kind, _, _, _, _ = trace_camera(
                C[0], C[1], C[2], dx, dy, dz, boxes, bmat, bpar, sph, gmeta, cstart, citems
            )
            depth[i, j] = t if kind != 0 else 0.0
