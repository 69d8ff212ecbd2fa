"""Image folders: listing by set and reading with clear errors."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".tif", ".tiff"}


class ImageError(ValueError):
    """A missing, unreadable or truncated image."""


def list_images(root: str | Path, sets: tuple[str, ...] = ("aerial", "ground")) -> list[str]:
    """Image names (`SET/FILE`, docs/formats.md) under root/SET/, sorted."""
    root = Path(root)
    if not root.is_dir():
        raise ImageError(f"image folder {root} does not exist")
    names = []
    for s in sets:
        d = root / s
        if d.is_dir():
            names += [f"{s}/{p.name}" for p in sorted(d.iterdir()) if p.suffix.lower() in IMAGE_SUFFIXES]
    return names


def read_image(path: str | Path, grayscale: bool = False) -> np.ndarray:
    """Decode an image (RGB uint8, or grayscale); raise ImageError if absent, unreadable or truncated."""
    path = Path(path)
    if not path.is_file():
        raise ImageError(f"{path}: no such image")
    data = np.fromfile(path, np.uint8)
    if path.suffix.lower() in (".jpg", ".jpeg") and not data[-2:].tobytes() == b"\xff\xd9":
        raise ImageError(f"{path}: truncated JPEG (no end-of-image marker)")
    img = cv2.imdecode(data, cv2.IMREAD_GRAYSCALE if grayscale else cv2.IMREAD_COLOR)
    if img is None:
        raise ImageError(f"{path}: cannot decode image")
    return img if grayscale else cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
