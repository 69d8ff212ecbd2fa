"""Coordinate frames: any EPSG CRS <-> WGS84 geodetic <-> a local East-North-Up frame (pyproj)."""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import pyproj

WGS84_3D = "EPSG:4979"
ECEF = "EPSG:4978"


class CRSError(ValueError):
    """An unknown or unusable coordinate reference system."""


@lru_cache(maxsize=64)
def parse_crs(code: str) -> pyproj.CRS:
    try:
        crs = pyproj.CRS.from_user_input(code)
    except pyproj.exceptions.CRSError as e:
        raise CRSError(f"unknown CRS {code!r}: {e}") from None
    if crs.is_geographic or crs.is_projected:
        return crs
    raise CRSError(f"CRS {code!r} is neither geographic nor projected")


def is_wgs84_geographic(code: str | None) -> bool:
    """Whether `code` is WGS84 latitude/longitude (EPSG:4326, EPSG:4979); None counts as WGS84."""
    return code is None or parse_crs(code).to_epsg() in (4326, 4979)


@lru_cache(maxsize=64)
def _transformer(src: str, dst: str) -> pyproj.Transformer:
    return pyproj.Transformer.from_crs(pyproj.CRS(src), pyproj.CRS(dst), always_xy=True)


def to_wgs84(crs: str, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, ...]:
    """Coordinates in `crs` (lat, lon, h for geographic; x, y, z for projected) -> (lat, lon, h)."""
    if parse_crs(crs).is_geographic:
        a, b = b, a  # always_xy: longitude first
    lon, lat, h = _transformer(crs, WGS84_3D).transform(a, b, c)
    return np.asarray(lat), np.asarray(lon), np.asarray(h)


def from_wgs84(crs: str, lat: np.ndarray, lon: np.ndarray, h: np.ndarray) -> tuple[np.ndarray, ...]:
    x, y, z = _transformer(WGS84_3D, crs).transform(lon, lat, h)
    if parse_crs(crs).is_geographic:
        return np.asarray(y), np.asarray(x), np.asarray(z)
    return np.asarray(x), np.asarray(y), np.asarray(z)


@dataclass(frozen=True)
class LocalFrame:
    """A local ENU frame in metres, tangent to the ellipsoid at (lat0, lon0, h0)."""

    lat0: float
    lon0: float
    h0: float

    def _rotation(self) -> np.ndarray:
        """Rows: E, N, U unit vectors in ECEF."""
        la, lo = np.radians(self.lat0), np.radians(self.lon0)
        return np.array(
            [
                [-np.sin(lo), np.cos(lo), 0.0],
                [-np.sin(la) * np.cos(lo), -np.sin(la) * np.sin(lo), np.cos(la)],
                [np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)],
            ]
        )

    def _origin_ecef(self) -> np.ndarray:
        return np.array(_transformer(WGS84_3D, ECEF).transform(self.lon0, self.lat0, self.h0))

    def from_wgs84(self, lat, lon, h) -> np.ndarray:
        """(lat, lon, h) arrays -> (N, 3) ENU."""
        x, y, z = _transformer(WGS84_3D, ECEF).transform(
            np.atleast_1d(lon), np.atleast_1d(lat), np.atleast_1d(h)
        )
        ecef = np.stack([x, y, z], -1) - self._origin_ecef()
        return ecef @ self._rotation().T

    def rotation_to_enu_at(self, lat: float, lon: float) -> np.ndarray:
        """(3, 3) rotation taking vectors of this frame to the ENU frame tangent at (lat, lon)."""
        return LocalFrame(lat, lon, 0.0)._rotation() @ self._rotation().T

    def to_wgs84(self, enu: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(N, 3) ENU -> (lat, lon, h) arrays."""
        ecef = np.atleast_2d(enu) @ self._rotation() + self._origin_ecef()
        lon, lat, h = _transformer(ECEF, WGS84_3D).transform(ecef[:, 0], ecef[:, 1], ecef[:, 2])
        return np.asarray(lat), np.asarray(lon), np.asarray(h)
