"""Camera geometry shared by the pipeline steps: cameras and poses (services.colmap_model), a camera
looking at a point, optical axes and the angles between directions and of rotations, cameras at a
smaller image size, poses of pycolmap images and of POS records in a local frame, depth maps read at pixels.
Conventions: world-to-camera poses (x_cam = R x_world + t), ENU world (z up), COLMAP pixels."""

from __future__ import annotations

import math

import numpy as np
import pycolmap

from services.colmap_model import Camera, Pose
from services.pos import LocalFrame, PosRecord

__all__ = [
    "Camera",
    "Pose",
    "angle_deg",
    "look_at",
    "lookup_depth",
    "optical_axis",
    "pitch_deg",
    "pos_in_frame",
    "rot_x",
    "pose_of_image",
    "rotation_angle_deg",
    "scaled_camera",
    "scaled_intrinsics",
]


def look_at(center: np.ndarray, target: np.ndarray, up: np.ndarray | None = None) -> Pose:
    """A camera at `center` looking at `target`, its image x axis level (perpendicular to `up`, ENU z);
    looking straight along `up`, the image top points north."""
    up = np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, float)
    z = np.asarray(target, float) - np.asarray(center, float)
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return Pose.from_center(np.stack([x, y, z], 1), center)


def rotation_angle_deg(R: np.ndarray) -> float:
    """The angle of a rotation matrix (3, 3), in degrees (0-180)."""
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


def pose_of_image(image: pycolmap.Image) -> Pose:
    """The world-to-camera pose of a registered pycolmap image."""
    return Pose.of_image(image)


def scaled_intrinsics(
    K: np.ndarray, width: int, height: int, max_width: int | None
) -> tuple[np.ndarray, int, int]:
    """K (3, 3) and size of an image downsampled to at most `max_width` pixels wide (COLMAP convention:
    the principal point scales with the image); unchanged for a falsy max_width."""
    if not max_width or width <= max_width:
        return np.asarray(K, float), width, height
    w = int(max_width)
    h = max(1, int(round(height * w / width)))
    S = np.diag([w / width, h / height, 1.0])
    return S @ K, w, h


def scaled_camera(camera: Camera, max_width: int, fov_scale: float = 1.0) -> Camera:
    """A PINHOLE copy of `camera` at most `max_width` wide; focal length divided by fov_scale."""
    s = min(1.0, max_width / camera.width)
    w, h = round(camera.width * s), round(camera.height * s)
    K = camera.K
    sx, sy = w / camera.width, h / camera.height
    return Camera(
        "PINHOLE", w, h, [K[0, 0] * sx / fov_scale, K[1, 1] * sy / fov_scale, K[0, 2] * sx, K[1, 2] * sy]
    )


def rot_x(theta: float) -> np.ndarray:
    """The rotation (3, 3) by theta radians about the x axis."""
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def optical_axis(pose: Pose) -> np.ndarray:
    """Unit optical axis in the world frame."""
    return pose.R[2] / np.linalg.norm(pose.R[2])


def pitch_deg(pose: Pose) -> float:
    """Elevation of the optical axis (0 horizontal, -90 nadir)."""
    return float(np.degrees(np.arcsin(np.clip(optical_axis(pose)[2], -1.0, 1.0))))


def angle_deg(u: np.ndarray, v: np.ndarray) -> float:
    """The angle between two directions, in degrees (0-180)."""
    u, v = np.asarray(u, float), np.asarray(v, float)
    c = float(u @ v / max(np.linalg.norm(u) * np.linalg.norm(v), 1e-12))
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def pos_in_frame(
    records: list[PosRecord], frame: LocalFrame, names: list[str] | None = None
) -> dict[str, tuple[Pose | None, np.ndarray, PosRecord]]:
    """{name: (pose or None without attitude, centre, record)} of POS records in a local frame."""
    recs = [r for r in records if names is None or r.name in set(names)]
    if not recs:
        return {}
    xyz = frame.from_wgs84(
        np.array([r.lat for r in recs]), np.array([r.lon for r in recs]), np.array([r.h for r in recs])
    ).reshape(-1, 3)
    out = {}
    for r, c in zip(recs, xyz, strict=True):
        pose = Pose.from_center(r.R_world_from_cam, c) if r.R_world_from_cam is not None else None
        out[r.name] = (pose, c, r)
    return out


def lookup_depth(depth: np.ndarray, uv: np.ndarray, interp: str = "bilinear") -> np.ndarray:
    """Depth (N,) at COLMAP pixels uv (N, 2); 0 outside the image or where there is no surface.

    Depth at row i, col j belongs to pixel (j + 0.5, i + 0.5). 'nearest' takes that pixel.
    'bilinear' interpolates the 2x2 pixel centres around uv where they are all valid and continuous
    (max/min <= 1.05), and falls back to nearest across depth edges, so that a sub-pixel keypoint on
    a slanted surface gets a sub-pixel accurate depth without blending foreground and background.
    """
    h, w = depth.shape
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    out = np.zeros(len(uv), np.float64)
    inside = np.isfinite(uv).all(1) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    if not inside.any():
        return out
    x, y = uv[inside, 0], uv[inside, 1]
    d = depth[np.minimum(y.astype(int), h - 1), np.minimum(x.astype(int), w - 1)].astype(np.float64)
    if interp == "bilinear":
        u, v = np.clip(x - 0.5, 0, w - 1), np.clip(y - 0.5, 0, h - 1)
        j0, i0 = (
            np.minimum(u.astype(int), w - 2 if w > 1 else 0),
            np.minimum(v.astype(int), h - 2 if h > 1 else 0),
        )
        j1, i1 = np.minimum(j0 + 1, w - 1), np.minimum(i0 + 1, h - 1)
        fu, fv = u - j0, v - i0
        q = np.stack([depth[i0, j0], depth[i0, j1], depth[i1, j0], depth[i1, j1]], 1).astype(np.float64)
        wts = np.stack([(1 - fu) * (1 - fv), fu * (1 - fv), (1 - fu) * fv, fu * fv], 1)
        ok = (q.min(1) > 0) & (q.max(1) <= 1.05 * q.min(1))
        d = np.where(ok, (q * wts).sum(1), d)
    elif interp != "nearest":
        raise ValueError(f"unknown depth interpolation {interp!r}")
    out[inside] = d
    return out


def horizontal(v: np.ndarray) -> np.ndarray | None:
    """The unit horizontal direction of v (3,); None when v is (nearly) vertical."""
    h = np.array([v[0], v[1], 0.0])
    n = np.linalg.norm(h)
    return h / n if n > 1e-6 else None
