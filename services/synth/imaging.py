"""Photo textures (mip-mapped atlas for the kernels) and the camera model after the renderer:
exposure, white balance, vignetting, sRGB encoding, sensor noise, JPEG."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

PHOTO_SUFFIXES = {".jpg", ".jpeg", ".png"}


def srgb_to_linear_lut() -> np.ndarray:
    """(256,) float64: 8-bit sRGB value -> linear light."""
    c = np.arange(256) / 255.0
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def list_photos(folder: Path) -> list[Path]:
    """Photos (jpg/png) in folder or its images/ subfolder, sorted by name."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    if (folder / "images").is_dir():
        folder = folder / "images"
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in PHOTO_SUFFIXES)


def photo_atlas(
    folder: Path | None, size: tuple[int, int] = (1024, 768), max_photos: int = 64
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Photos resized to `size` (w, h) with their mip chains packed into one flat uint8 RGB array.

    Returns atlas (K,) uint8, aoff (N, L) int64 offsets of level l of photo n, adim (N, L, 2) int64
    (height, width) per level. Without photos: a 1x1 grey dummy (the kernels then never sample it).
    """
    paths = list_photos(folder)[:max_photos] if folder is not None else []
    if not paths:
        return np.full(3, 128, np.uint8), np.zeros((1, 1), np.int64), np.ones((1, 1, 2), np.int64)
    w, h = size
    nlev = int(np.floor(np.log2(min(w, h)))) - 2
    chunks, off, dims, pos = (
        [],
        np.zeros((len(paths), nlev), np.int64),
        np.zeros((len(paths), nlev, 2), np.int64),
        0,
    )
    for n, p in enumerate(paths):
        img = cv2.imread(str(p), cv2.IMREAD_COLOR)
        if img is None:
            raise ValueError(f"cannot read texture photo {p}")
        img = cv2.cvtColor(cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA), cv2.COLOR_BGR2RGB)
        for lev in range(nlev):
            if lev:
                img = cv2.resize(
                    img, (max(img.shape[1] // 2, 1), max(img.shape[0] // 2, 1)), interpolation=cv2.INTER_AREA
                )
            off[n, lev] = pos
            dims[n, lev] = img.shape[:2]
            chunks.append(np.ascontiguousarray(img).ravel())
            pos += img.size
    return np.concatenate(chunks), off, dims


def develop(radiance: np.ndarray, conf: dict, rng: np.random.Generator) -> np.ndarray:
    """Linear radiance (H, W, 3) -> 8-bit sRGB (H, W, 3) uint8 with exposure, white balance, vignetting
    (1 - v r^2, r = 1 in the corners) and sensor noise (read noise + shot noise, in DN)."""
    h, w = radiance.shape[:2]
    x = radiance.astype(np.float64) * conf["exposure"] * np.asarray(conf["wb"], float)
    yy, xx = np.mgrid[0:h, 0:w]
    r2 = ((xx + 0.5 - w / 2) ** 2 + (yy + 0.5 - h / 2) ** 2) / ((w / 2) ** 2 + (h / 2) ** 2)
    x *= (1.0 - conf["vignetting"] * r2)[..., None]
    dn = 255.0 * linear_to_srgb(x)
    sigma = np.sqrt(conf["read_noise"] ** 2 + conf["shot_noise"] * dn)
    dn = dn + sigma * rng.standard_normal(dn.shape)
    return np.clip(np.rint(dn), 0, 255).astype(np.uint8)


def encode_jpeg(rgb: np.ndarray, quality: int) -> bytes:
    ok, buf = cv2.imencode(
        ".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, int(quality)]
    )
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    return buf.tobytes()
