"""POS and an intrinsics prior from the images themselves: EXIF GPS and DJI XMP metadata.

- Position: EXIF GPSLatitude/GPSLongitude, and GPSAltitude (or XMP drone-dji:AbsoluteAltitude) as the
  height. EXIF altitudes are above mean sea level; without a geoid grid (pyproj here has none) they are
  kept as they are, so `h` is off from the ellipsoidal height by the geoid undulation (a constant over
  one flight: it shifts the local frame, not the geometry). `altitude="relative"` uses XMP
  drone-dji:RelativeAltitude (above the take-off point) plus `takeoff_h` instead.
- Attitude: XMP drone-dji:GimbalYawDegree/GimbalPitchDegree/GimbalRollDegree, which are our ypr
  convention (yaw clockwise from north, pitch -90 = nadir; docs/formats.md). FlightYaw/Pitch/Roll (the
  aircraft body) are read but not used for the camera.
- Accuracy: DJI RTK models write drone-dji:RtkStdLon/RtkStdLat/RtkStdHgt (metres); used when present.
- Intrinsics: SIMPLE_RADIAL with f_px = FocalLengthIn35mmFilm * diagonal_px / 43.27 (the 35 mm
  film diagonal), else f_px = FocalLength (mm) * FocalPlaneXResolution (pixels per mm, after
  FocalPlaneResolutionUnit) * width / PixelXDimension; principal point at the centre, no distortion.

A flat folder of images (no `aerial/` or `ground/` inside) is one aerial set: its images are named
`aerial/<file>` (docs/formats.md).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from PIL import Image, UnidentifiedImageError

from shared.images import IMAGE_SUFFIXES, ImageError, list_images, read_image

from .attitude import ypr_to_matrix
from .records import PosError, PosRecord
from .rows import LAT_RANGE, LON_RANGE, check_number

if TYPE_CHECKING:
    from services.colmap_model import Camera

EXIF_CRS = "EPSG:4326"  # EXIF GPS: WGS84 latitude and longitude (altitude above sea level)
FILM_DIAGONAL_MM = 43.27  # diagonal of a 36 x 24 mm frame
XMP_SCAN_BYTES = 256 * 1024  # XMP packets sit in an APP1 segment near the start of a JPEG
_XMP_ATTR = re.compile(rb'drone-dji:(\w+)\s*=\s*"([^"]*)"')
_XMP_ELEM = re.compile(rb"<drone-dji:(\w+)>([^<]*)</drone-dji:\1>")
_GPS_IFD, _EXIF_IFD = 0x8825, 0x8769
_TAG_MAKE, _TAG_MODEL, _TAG_FOCAL, _TAG_FOCAL35 = 0x010F, 0x0110, 0x920A, 0xA405
_TAG_FP_XRES, _TAG_FP_UNIT, _TAG_PIXEL_X = 0xA20E, 0xA210, 0xA002
FOCAL_PLANE_UNIT_MM = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}  # EXIF FocalPlaneResolutionUnit: inch, cm, mm, um


@dataclass
class ExifData:
    """Metadata of one image; None where the image does not say."""

    width: int
    height: int
    lat: float | None = None
    lon: float | None = None
    alt: float | None = None  # EXIF GPSAltitude (above sea level) or XMP AbsoluteAltitude
    rel_alt: float | None = None  # XMP RelativeAltitude (above the take-off point)
    gimbal_ypr: tuple[float, float, float] | None = None
    flight_ypr: tuple[float, float, float] | None = None
    rtk_std: tuple[float, float, float] | None = None  # (lon, lat, height) metres
    focal_mm: float | None = None
    focal_35mm: float | None = None
    focal_plane_px_per_mm: float | None = None  # EXIF FocalPlaneXResolution in pixels per millimetre ...
    focal_plane_width_px: int | None = None  # ... of an image this wide (EXIF PixelXDimension)
    make: str | None = None
    model: str | None = None


# -- image files -------------------------------------------------------------------------------
def image_paths(folder: str | Path, flat_set: str = "aerial") -> dict[str, Path]:
    """{image name: file} of an `images/` folder (aerial/, ground/ inside) or of a flat image folder.

    The images of a flat folder form the set `flat_set`: `aerial/DJI_0018.JPG`.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise ImageError(f"image folder {folder} does not exist")
    names = list_images(folder)
    if names:
        return {n: folder / n for n in names}
    files = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise ImageError(f"{folder}: no images (neither aerial/ nor ground/ nor image files)")
    return {f"{flat_set}/{p.name}": p for p in files}


def check_image(path: str | Path, decode: bool = False) -> tuple[int, int]:
    """(width, height) of an image; ImageError when it is missing, unreadable or truncated.

    Without `decode` only the header is parsed and a JPEG must end with its end-of-image marker;
    with it the whole image is decoded (shared.images.read_image).
    """
    path = Path(path)
    if decode:
        img = read_image(path, grayscale=True)
        return int(img.shape[1]), int(img.shape[0])
    if not path.is_file():
        raise ImageError(f"{path}: no such image")
    try:
        with Image.open(path) as im:
            size = im.size
    except (UnidentifiedImageError, OSError, Image.DecompressionBombError) as e:
        raise ImageError(f"{path}: cannot read image ({e})") from None
    if path.suffix.lower() in (".jpg", ".jpeg"):
        with open(path, "rb") as f:
            f.seek(-2, 2)
            if f.read(2) != b"\xff\xd9":
                raise ImageError(f"{path}: truncated JPEG (no end-of-image marker)")
    return int(size[0]), int(size[1])


# -- metadata ----------------------------------------------------------------------------------
def _float(v) -> float | None:
    try:
        f = float(v)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return f if math.isfinite(f) else None


def _dms(value, ref) -> float | None:
    """Degrees of an EXIF (deg, min, sec) triple and its N/S/E/W reference."""
    try:
        d, m, s = (float(v) for v in value)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    deg = d + m / 60.0 + s / 3600.0
    ref = ref.decode(errors="ignore") if isinstance(ref, bytes) else str(ref or "")
    return -deg if ref.strip().upper() in ("S", "W") else deg


def read_xmp(path: str | Path) -> dict[str, str]:
    """drone-dji:* XMP properties (attributes or elements) of an image, {} if none."""
    with open(path, "rb") as f:
        head = f.read(XMP_SCAN_BYTES)
    out = {k.decode(): v.decode(errors="ignore").strip() for k, v in _XMP_ATTR.findall(head)}
    out.update({k.decode(): v.decode(errors="ignore").strip() for k, v in _XMP_ELEM.findall(head)})
    return out


def _triple(xmp: dict[str, str], keys: tuple[str, str, str]) -> tuple[float, float, float] | None:
    vals = [_float(xmp.get(k)) for k in keys]
    return None if any(v is None for v in vals) else tuple(vals)  # type: ignore[return-value]


def read_exif(path: str | Path) -> ExifData:
    """EXIF GPS, focal lengths and DJI XMP of one image (ImageError if unreadable or truncated)."""
    path = Path(path)
    width, height = check_image(path)
    try:
        with Image.open(path) as im:
            exif = im.getexif()
            gps = exif.get_ifd(_GPS_IFD)
            sub = exif.get_ifd(_EXIF_IFD)
    except (OSError, SyntaxError, ValueError, Image.DecompressionBombError) as e:
        raise ImageError(f"{path}: cannot read EXIF ({e})") from None
    make, model = (str(exif.get(t) or "").strip("\x00 ") or None for t in (_TAG_MAKE, _TAG_MODEL))
    data = ExifData(width, height, make=make, model=model)
    if 2 in gps and 4 in gps:
        data.lat, data.lon = _dms(gps[2], gps.get(1, "N")), _dms(gps[4], gps.get(3, "E"))
    if 6 in gps:
        alt = _float(gps[6])
        ref = gps.get(5, 0)
        below = (ref[:1] == b"\x01") if isinstance(ref, bytes) else ref == 1
        data.alt = None if alt is None else (-alt if below else alt)
    data.focal_mm = _float(sub.get(_TAG_FOCAL))
    data.focal_35mm = _float(sub.get(_TAG_FOCAL35)) or None
    res, unit = _float(sub.get(_TAG_FP_XRES)), sub.get(_TAG_FP_UNIT, 2)  # EXIF's default unit: inch
    if res and res > 0 and unit in FOCAL_PLANE_UNIT_MM:
        data.focal_plane_px_per_mm = res / FOCAL_PLANE_UNIT_MM[unit]
        pixel_x = _float(sub.get(_TAG_PIXEL_X))
        data.focal_plane_width_px = int(pixel_x) if pixel_x and pixel_x > 0 else None
    xmp = read_xmp(path)
    if data.alt is None:
        data.alt = _float(xmp.get("AbsoluteAltitude"))
    data.rel_alt = _float(xmp.get("RelativeAltitude"))
    data.gimbal_ypr = _triple(xmp, ("GimbalYawDegree", "GimbalPitchDegree", "GimbalRollDegree"))
    data.flight_ypr = _triple(xmp, ("FlightYawDegree", "FlightPitchDegree", "FlightRollDegree"))
    data.rtk_std = _triple(xmp, ("RtkStdLon", "RtkStdLat", "RtkStdHgt"))
    return data


def focal_px(data: ExifData) -> float | None:
    """Focal length in pixels: from the 35 mm equivalent (over the film diagonal), else from FocalLength
    (mm) and the sensor's FocalPlaneXResolution (pixels per mm at PixelXDimension pixels across, scaled
    to this image's width); None when the EXIF gives neither."""
    if data.focal_35mm:
        return data.focal_35mm * math.hypot(data.width, data.height) / FILM_DIAGONAL_MM
    if data.focal_mm and data.focal_mm > 0 and data.focal_plane_px_per_mm:
        scale = data.width / (data.focal_plane_width_px or data.width)  # a resized copy keeps the EXIF
        return data.focal_mm * data.focal_plane_px_per_mm * scale
    return None


def camera_from_exif(data: ExifData) -> Camera | None:
    """SIMPLE_RADIAL prior from the EXIF focal length (`focal_px`); None when the EXIF lacks it."""
    from services.colmap_model import Camera  # pycolmap: imported only when needed

    f = focal_px(data)
    if f is None:
        return None
    return Camera("SIMPLE_RADIAL", data.width, data.height, [f, data.width / 2.0, data.height / 2.0, 0.0])


def record_from_exif(
    name: str,
    data: ExifData,
    altitude: str = "gps",
    attitude: str = "gimbal",
    takeoff_h: float = 0.0,
    errors: list[str] | None = None,
) -> PosRecord | None:
    """A PosRecord from parsed metadata, or None (with a message in `errors`) when incomplete or invalid."""
    errors = [] if errors is None else errors
    where = f"image {name!r}"
    if data.lat is None or data.lon is None:
        errors.append(f"{where}: no GPS position in its EXIF")
        return None
    if altitude == "relative":
        h = None if data.rel_alt is None else data.rel_alt + takeoff_h
        what = "XMP RelativeAltitude"
    else:
        h, what = data.alt, "GPS altitude"
    if h is None:
        errors.append(f"{where}: no {what} in its metadata")
        return None
    n = len(errors)
    lat = check_number(errors, where, "GPSLatitude", data.lat, LAT_RANGE)
    lon = check_number(errors, where, "GPSLongitude", data.lon, LON_RANGE)
    R = None
    if attitude == "gimbal" and data.gimbal_ypr is not None:
        R = ypr_to_matrix(*data.gimbal_ypr)
    if len(errors) > n:
        return None
    std_xy = std_z = None
    if data.rtk_std is not None:
        std_xy, std_z = max(data.rtk_std[0], data.rtk_std[1]), data.rtk_std[2]
    return PosRecord(
        name, float(lat), float(lon), float(h), R, std_xy, std_z, crs=EXIF_CRS, rel_alt=data.rel_alt
    )  # type: ignore[arg-type]


def read_pos_exif(
    folder: str | Path,
    names: list[str] | None = None,
    altitude: str = "gps",
    attitude: str = "gimbal",
    takeoff_h: float = 0.0,
) -> list[PosRecord]:
    """POS records of the images of a folder (or of `names` in it) from their EXIF/XMP.

    Raises PosError naming every image that is unreadable, truncated, or lacks a usable GPS position.
    """
    if altitude not in ("gps", "relative"):
        raise ValueError(f"altitude must be gps or relative, not {altitude!r}")
    if attitude not in ("gimbal", "none"):
        raise ValueError(f"attitude must be gimbal or none, not {attitude!r}")
    try:
        paths = image_paths(folder)
    except ImageError as e:
        raise PosError([str(e)]) from None
    errors: list[str] = []
    if names is not None:
        errors += [f"image {n!r}: not in {folder}" for n in names if n not in paths]
        paths = {n: paths[n] for n in names if n in paths}
    records = []
    for name, path in paths.items():
        try:
            data = read_exif(path)
        except ImageError as e:
            errors.append(f"image {name!r}: {e}")
            continue
        rec = record_from_exif(name, data, altitude, attitude, takeoff_h, errors)
        if rec is not None:
            records.append(rec)
    if errors:
        raise PosError(errors)
    return records
