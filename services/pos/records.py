"""POS records and their validation against a set of images."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np


class PosError(ValueError):
    """Invalid POS input. `errors` lists one message per bad row or image."""

    def __init__(self, errors: list[str]):
        self.errors = list(errors)
        shown = self.errors[:20]
        more = f"\n  ... and {len(self.errors) - 20} more" if len(self.errors) > 20 else ""
        super().__init__("invalid POS:\n  " + "\n  ".join(shown) + more)


# the uncertainty assumed where a POS states none (consumer GNSS in EXIF, a gimbal's attitude)
DEFAULT_STD_XY = 3.0  # metres
DEFAULT_STD_Z = 5.0  # metres
DEFAULT_STD_ATT = 5.0  # degrees


@dataclass
class PosRecord:
    """Position (WGS84, ellipsoidal height) and optional attitude of one image."""

    name: str
    lat: float
    lon: float
    h: float
    R_world_from_cam: np.ndarray | None = None  # (3, 3), local ENU at the image, COLMAP camera frame
    std_xy: float | None = None  # metres
    std_z: float | None = None  # metres
    std_att: float | None = None  # degrees
    crs: str | None = None  # the CRS of the POS source (positions here are WGS84 whatever it was)
    rel_alt: float | None = None  # metres above the take-off point (DJI XMP RelativeAltitude)

    def std_or_default(self) -> tuple[float, float, float]:
        """(std_xy m, std_z m, std_att deg), the defaults where the POS states none."""
        return (
            self.std_xy or DEFAULT_STD_XY,
            self.std_z or DEFAULT_STD_Z,
            self.std_att or DEFAULT_STD_ATT,
        )

    @property
    def image_set(self) -> str:
        return self.name.split("/", 1)[0] if "/" in self.name else ""


def check_against_images(records: Iterable[PosRecord], image_names: Iterable[str]) -> None:
    """Raise PosError naming images without POS and POS rows without an image."""
    have = {r.name for r in records}
    images = set(image_names)
    errors = [f"image {n!r} has no POS row" for n in sorted(images - have)]
    errors += [f"POS row {n!r} names no uploaded image" for n in sorted(have - images)]
    if errors:
        raise PosError(errors)
