"""Camera attitude conventions and their rotation matrices (see docs/formats.md).

All matrices here are `R_world_from_cam` in a local East-North-Up frame, for the COLMAP camera
frame (x right, y down, z along the optical axis).
"""

from __future__ import annotations

import numpy as np

# Columns: the camera's x, y, z axes in ENU for yaw = pitch = roll = 0 (looking north, x east).
_B = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
_PHOTO_TO_CAM = np.diag([1.0, -1.0, -1.0])


def rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def ypr_to_matrix(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """Gimbal yaw (clockwise from north), pitch (elevation), roll in degrees -> R_world_from_cam."""
    y, p, r = np.radians([yaw, pitch, roll])
    return rot_z(-y) @ _B @ rot_x(p) @ rot_z(r)


def matrix_to_ypr(R: np.ndarray) -> tuple[float, float, float]:
    """Inverse of `ypr_to_matrix`, in degrees; yaw in [0, 360). Roll is 0 at the pitch = +-90 singularity
    and the whole rotation goes into yaw."""
    f = R[:, 2]  # optical axis in ENU
    pitch = np.degrees(np.arcsin(np.clip(f[2], -1.0, 1.0)))
    if np.hypot(f[0], f[1]) > 1e-9:
        yaw = np.degrees(np.arctan2(f[0], f[1]))
    else:  # looking straight up or down: the heading is that of the image's top (-y axis)
        up = -R[:, 1] * (-np.sign(f[2]))
        yaw = np.degrees(np.arctan2(up[0], up[1]))
    M = (rot_z(-np.radians(yaw)) @ _B @ rot_x(np.radians(pitch))).T @ R
    roll = np.degrees(np.arctan2(M[1, 0], M[0, 0]))
    return float(yaw % 360.0), float(pitch), float(roll)


def opk_to_matrix(omega: float, phi: float, kappa: float) -> np.ndarray:
    """Photogrammetric omega/phi/kappa in degrees -> R_world_from_cam (COLMAP camera frame)."""
    o, p, k = np.radians([omega, phi, kappa])
    return rot_x(o) @ rot_y(p) @ rot_z(k) @ _PHOTO_TO_CAM


def matrix_to_opk(R: np.ndarray) -> tuple[float, float, float]:
    """Inverse of `opk_to_matrix`, in degrees."""
    P = R @ _PHOTO_TO_CAM  # = Rx(o) Ry(p) Rz(k)
    phi = np.arcsin(np.clip(P[0, 2], -1.0, 1.0))
    omega = np.arctan2(-P[1, 2], P[2, 2])
    kappa = np.arctan2(-P[0, 1], P[0, 0])
    return tuple(float(v) for v in np.degrees([omega, phi, kappa]))  # type: ignore[return-value]
