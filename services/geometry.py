"""Camera geometry shared by the pipeline steps: cameras and poses (services.colmap_model), a camera
looking at a point, the angle of a rotation, cameras at a smaller image size, and poses of pycolmap
images. Conventions: world-to-camera poses (x_cam = R x_world + t), ENU world (z up), COLMAP pixels."""

from __future__ import annotations

import numpy as np
import pycolmap

from services.colmap_model import Camera, Pose

__all__ = [
    "Camera",
    "Pose",
    "look_at",
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
    m = np.asarray(image.cam_from_world().matrix())
    return Pose(m[:, :3].copy(), m[:, 3].copy())


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
