"""Small bridge between plain arrays and pycolmap models: cameras, poses, reading and writing."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import pycolmap


@dataclass
class Camera:
    """A COLMAP camera. For PINHOLE, params = [fx, fy, cx, cy] (COLMAP pixel convention)."""

    model: str
    width: int
    height: int
    params: list[float]

    @property
    def K(self) -> np.ndarray:
        if self.model == "PINHOLE":
            fx, fy, cx, cy = self.params
        elif self.model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
            fx = fy = self.params[0]
            cx, cy = self.params[1:3]
        else:  # OPENCV and friends: fx, fy, cx, cy first
            fx, fy, cx, cy = self.params[:4]
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    def to_pycolmap(self, camera_id: int) -> pycolmap.Camera:
        return pycolmap.Camera(
            model=self.model, width=self.width, height=self.height, params=self.params, camera_id=camera_id
        )

    @classmethod
    def from_pycolmap(cls, cam: pycolmap.Camera) -> Camera:
        return cls(cam.model.name, int(cam.width), int(cam.height), [float(p) for p in cam.params])


@dataclass
class Pose:
    """cam_from_world: X_cam = R @ X_world + t."""

    R: np.ndarray
    t: np.ndarray

    @property
    def center(self) -> np.ndarray:
        return -self.R.T @ self.t

    @classmethod
    def of_image(cls, image: pycolmap.Image) -> Pose:
        """The world-to-camera pose of a registered pycolmap image."""
        m = np.asarray(image.cam_from_world().matrix())
        return cls(m[:, :3].copy(), m[:, 3].copy())

    @classmethod
    def from_center(cls, R_world_from_cam: np.ndarray, center: np.ndarray) -> Pose:
        R = R_world_from_cam.T
        return cls(R, -R @ np.asarray(center, float))

    def project(self, K: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World points (N, 3) -> pixels (N, 2) in COLMAP convention and depths (N,)."""
        Xc = X @ self.R.T + self.t
        z = Xc[:, 2]
        uv = Xc[:, :2] / np.where(np.abs(z) < 1e-12, 1e-12, z)[:, None]
        return uv * np.diag(K)[:2] + K[:2, 2], z

    def unproject(self, K: np.ndarray, uv: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) with z-depths (N,) -> world points (N, 3)."""
        xy = (uv - K[:2, 2]) / np.diag(K)[:2]
        Xc = np.concatenate([xy, np.ones((len(uv), 1))], 1) * depth[:, None]
        return (Xc - self.t) @ self.R


def write_model(
    path: str | Path,
    cameras: dict[str, Camera],
    images: dict[str, tuple[str, Pose]],
    points: np.ndarray | None = None,
    colors: np.ndarray | None = None,
) -> Path:
    """Write a COLMAP binary model. `images` maps image name -> (camera key, pose)."""
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    rec = pycolmap.Reconstruction()
    cam_ids = {}
    for i, (key, cam) in enumerate(sorted(cameras.items()), start=1):
        rec.add_camera_with_trivial_rig(cam.to_pycolmap(i))
        cam_ids[key] = i
    for image_id, (name, (key, pose)) in enumerate(sorted(images.items()), start=1):
        img = pycolmap.Image(name=name, camera_id=cam_ids[key], image_id=image_id)
        rec.add_image_with_trivial_frame(
            img, pycolmap.Rigid3d(pycolmap.Rotation3d(pose.R), np.asarray(pose.t, float))
        )
    if points is not None:
        cols = colors if colors is not None else np.full((len(points), 3), 128, np.uint8)
        for X, c in zip(points, cols, strict=True):
            rec.add_point3D(np.asarray(X, float), pycolmap.Track(), np.asarray(c, np.uint8))
    rec.write(str(path))
    return path


def read_model(path: str | Path) -> tuple[dict[str, Camera], dict[str, Pose]]:
    """Registered images of a COLMAP model: ({name: camera}, {name: pose})."""
    rec = pycolmap.Reconstruction(str(path))
    cams, poses = {}, {}
    for img in rec.images.values():
        if not img.has_pose:
            continue
        cams[img.name] = Camera.from_pycolmap(img.camera)
        poses[img.name] = Pose.of_image(img)
    return cams, poses


def write_cameras_json(path: str | Path, cameras: dict[str, Camera]) -> Path:
    path = Path(path)
    path.write_text(json.dumps({k: asdict(c) for k, c in sorted(cameras.items())}, indent=1))
    return path


def read_cameras_json(path: str | Path) -> dict[str, Camera]:
    return {k: Camera(**v) for k, v in json.loads(Path(path).read_text()).items()}
