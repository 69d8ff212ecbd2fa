"""Wall materials cut from real facade photos: crops of brick walls only (no window, sky, plant or
street in them), mip-mapped into an atlas that the kernels tile over a facade (mirrored, so the tiles
meet without seams), at the crop's own scale.

The crops come from `../shared/data/lund_street` (BSD-2); each names its photo, its box in the photo's
1024 x 768 pixels and its scale, measured from the brick courses (77 mm from course to course, the
autocorrelation period of the crop's rows).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from .imaging import list_photos

WALL_CROPS: tuple[dict, ...] = (
    {"photo": "26.jpg", "box": (785, 125, 850, 330), "m_per_px": 0.0154},  # red brick, frontal
    {"photo": "26.jpg", "box": (940, 150, 1000, 300), "m_per_px": 0.0154},  # the same wall, right of a window
    {"photo": "27.jpg", "box": (905, 70, 985, 400), "m_per_px": 0.0096},  # orange brick pier
)
LEVELS = 4  # mip levels of every crop (the smallest crop is 60 px wide: 60, 30, 15, 8)


def wall_atlas(folder: Path, crops: tuple[dict, ...] = WALL_CROPS) -> tuple[np.ndarray, ...]:
    """The crops of photos in `folder` (its images/ subfolder, as list_photos) packed as
    imaging.photo_atlas packs photos: (atlas (K,) uint8, aoff (N, LEVELS), adim (N, LEVELS, 2), and
    m_per_px (N,)); FileNotFoundError when a crop's photo is missing."""
    by_name = {p.name: p for p in list_photos(Path(folder))}
    chunks, off, dims, pos = (
        [],
        np.zeros((len(crops), LEVELS), np.int64),
        np.zeros((len(crops), LEVELS, 2), np.int64),
        0,
    )
    for n, c in enumerate(crops):
        path = by_name.get(c["photo"])
        img = cv2.imread(str(path), cv2.IMREAD_COLOR) if path is not None else None
        if img is None:
            raise FileNotFoundError(f"wall texture photo {c['photo']} is not in {folder}")
        x0, y0, x1, y1 = c["box"]
        img = cv2.cvtColor(np.ascontiguousarray(img[y0:y1, x0:x1]), cv2.COLOR_BGR2RGB)
        for lev in range(LEVELS):
            if lev:
                size = (max(img.shape[1] // 2, 1), max(img.shape[0] // 2, 1))
                img = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
            off[n, lev] = pos
            dims[n, lev] = img.shape[:2]
            chunks.append(np.ascontiguousarray(img).ravel())
            pos += img.size
    m_per_px = np.array([c["m_per_px"] for c in crops], np.float64)
    return np.concatenate(chunks), off, dims, m_per_px
