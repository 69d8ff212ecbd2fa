"""A dense surface of the scene from the aerial images alone: stereo on rectified pairs, fused in a TSDF.

The 3DGS's depth at the intermediate views is its weakest part on the CPU (floaters, bumps, see-through
facades) and the plane proxy (services.views.proxy) has no plane where the sparse model has no points.
Classic two-view dense stereo does not depend on either: every aerial image forms pairs with the
neighbours that see the most of the same sparse points from a sideways baseline (the epipole far outside
the image); the pair is rectified (cv2.stereoRectify on the COLMAP poses), semi-global matching
(cv2.StereoSGBM, disparity range from the pair's sparse points, left-right check) gives a disparity map,
and its depth maps of all pairs are fused in a truncated signed distance volume (open3d, Curless &
Levoy 1996): a voxel's surface is what the images agree on, a floater seen through by other images is
carved away. The mesh of the volume is ray cast at any camera (open3d RaycastingScene).

    surface = StereoSurface.build("sfm/sparse", "images")     # an aerial COLMAP model and its images
    depth = surface.depth(camera, pose)                         # z-depth (H, W), 0 = no surface
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pycolmap

from services.colmap_model import Camera, Pose
from services.digests import sha256_file

logger = logging.getLogger("midview.views.stereo")

confs: dict[str, dict[str, Any]] = {
    "default": {
        "width": 800,  # the pairs are matched at this width (the sources' full resolution halved here)
        "pairs_per_image": 2,
        "min_shared": 50,  # sparse points a pair must share
        "max_axis_angle_deg": 30.0,  # between the two optical axes
        "max_epipole_cos": 0.35,  # |baseline . optical axis| / |baseline|: sideways pairs only
        "min_base_ratio": 0.05,  # baseline over the median depth of the shared points
        "max_disparities": 512,
        "block_size": 5,
        "uniqueness": 10,
        "disp12_max_diff": 1,
        "speckle_window": 100,
        "speckle_range": 2,
        "voxel_m": 0.12,
        "fuse_width": 800,  # depth maps wider than this are reduced to it for the fusion
        "block_count": 200000,  # voxel blocks (8^3 voxels) first allocated
        "min_weight": 1.5,  # a surface at least two pairs agree on
        "sdf_trunc_m": 0.3,
        "max_depth_m": 400.0,
    },
}


def _dist_coeffs(cam: pycolmap.Camera) -> tuple[np.ndarray, np.ndarray]:
    """(K (3, 3), OpenCV distortion coefficients) of a COLMAP camera (pinhole and radial models)."""
    p = np.asarray(cam.params, float)
    name = cam.model.name
    if name in ("SIMPLE_PINHOLE", "PINHOLE"):
        return cam.calibration_matrix(), np.zeros(5)
    if name == "SIMPLE_RADIAL":
        return cam.calibration_matrix(), np.array([p[3], 0, 0, 0, 0])
    if name == "RADIAL":
        return cam.calibration_matrix(), np.array([p[3], p[4], 0, 0, 0])
    if name == "OPENCV":
        return cam.calibration_matrix(), np.array([p[4], p[5], p[6], p[7], 0])
    raise ValueError(f"stereo: camera model {name} is not supported")


def shared_points(rec: pycolmap.Reconstruction) -> dict[tuple[int, int], int]:
    """{(image id a, image id b), a < b: the sparse points both images see}."""
    shared: dict[tuple[int, int], int] = {}
    for p in rec.points3D.values():
        ids = sorted({el.image_id for el in p.track.elements})
        for a in range(len(ids)):
            for b in range(a + 1, len(ids)):
                shared[(ids[a], ids[b])] = shared.get((ids[a], ids[b]), 0) + 1
    return shared


def voxel_means(V: np.ndarray, voxel_m: float) -> np.ndarray:
    """The mean of the points V (N, 3) in each voxel of voxel_m metres: (M, 3)."""
    if not len(V):
        return np.zeros((0, 3))
    cells = np.floor(V / np.float32(voxel_m)).astype(np.int64)
    cells -= cells.min(axis=0)
    span = cells.max(axis=0) + 1
    keys = (cells[:, 0] * span[1] + cells[:, 1]) * span[2] + cells[:, 2]  # one int64 per voxel
    del cells
    _, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    del keys
    sums = [np.bincount(inverse, weights=V[:, k], minlength=len(counts)) for k in range(3)]
    return np.stack(sums, 1) / counts[:, None]


def stereo_pairs(rec: pycolmap.Reconstruction, conf: dict) -> list[tuple[int, int, int]]:
    """(image id, image id, shared points) of the pairs to match: for every image its
    `pairs_per_image` best partners by shared sparse points among those with a sideways baseline."""
    shared = shared_points(rec)
    poses = {i: Pose.of_image(im) for i, im in rec.images.items() if im.has_pose}
    depth = {}  # median depth of each image's sparse points
    for i, pose in poses.items():
        X = [rec.points3D[p.point3D_id].xyz for p in rec.images[i].points2D if p.has_point3D()]
        depth[i] = float(np.median((np.asarray(X) @ pose.R[2]) + pose.t[2])) if X else 0.0
    cos_axis = np.cos(np.radians(conf["max_axis_angle_deg"]))
    chosen: set[tuple[int, int]] = set()
    partners: dict[int, list[tuple[int, int]]] = {i: [] for i in poses}
    for (a, b), n in shared.items():
        if n < conf["min_shared"] or a not in poses or b not in poses:
            continue
        za, zb = poses[a].R[2], poses[b].R[2]
        if float(za @ zb) < cos_axis:
            continue
        base = poses[b].center - poses[a].center
        nb = float(np.linalg.norm(base))
        if nb < conf["min_base_ratio"] * max(depth[a], depth[b]):
            continue
        if max(abs(float(base @ za)), abs(float(base @ zb))) / nb > conf["max_epipole_cos"]:
            continue
        partners[a].append((n, b))
        partners[b].append((n, a))
    for a, lst in partners.items():
        for _, b in sorted(lst, reverse=True)[: conf["pairs_per_image"]]:
            chosen.add((min(a, b), max(a, b)))
    return [(a, b, shared[(a, b)]) for a, b in sorted(chosen)]


def _disparity_range(
    rec: pycolmap.Reconstruction, ima, imb, pa: Pose, pb: Pose, rect: tuple[np.ndarray, ...]
) -> tuple[int, int, int] | None:
    """(rectified axis 0 or 1, smallest disparity, number of disparities, a multiple of 16) that hold
    the sparse points both images see, with a margin; None with fewer than 10 such points."""
    R1, R2, P1, P2 = rect
    ids_a = {p.point3D_id for p in ima.points2D if p.has_point3D()}
    ids = [p.point3D_id for p in imb.points2D if p.has_point3D() and p.point3D_id in ids_a]
    if len(ids) < 10:
        return None
    X = np.array([rec.points3D[i].xyz for i in ids])
    axis = 0 if abs(P2[0, 3]) >= abs(P2[1, 3]) else 1  # horizontal or vertical rectification
    xa = np.c_[(X @ pa.R.T + pa.t) @ R1.T, np.ones(len(X))] @ P1.T
    xb = ((X @ pb.R.T + pb.t) @ R2.T) @ P2[:, :3].T  # P2's last column is for points in frame 1
    d = xa[:, axis] / xa[:, 2] - xb[:, axis] / xb[:, 2]
    lo, hi = np.percentile(d, [1, 99])
    span = hi - lo
    min_d = int(np.floor(lo - 0.1 * span - 8))
    return axis, min_d, int(np.ceil((hi + 0.1 * span + 8 - min_d) / 16.0)) * 16


def _sgbm(conf: dict, num: int):
    """OpenCV's semi-global matcher searching disparities [0, num)."""
    bs = int(conf["block_size"])
    return cv2.StereoSGBM_create(
        minDisparity=0,
        numDisparities=num,
        blockSize=bs,
        P1=8 * bs * bs,
        P2=32 * bs * bs,
        disp12MaxDiff=int(conf["disp12_max_diff"]),
        uniquenessRatio=int(conf["uniqueness"]),
        speckleWindowSize=int(conf["speckle_window"]),
        speckleRange=int(conf["speckle_range"]),
        mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    )


def pair_depth(
    rec: pycolmap.Reconstruction, a: int, b: int, image_dir: Path, conf: dict
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Depth (H, W) of the rectified first image of pair (a, b), with its intrinsics K (3, 3, COLMAP's
    pixel convention) and its world-to-camera [R | t] (3, 4); None when the pair's disparity range
    cannot be found."""
    ima, imb = rec.images[a], rec.images[b]
    to_cv = np.array([[1.0, 0.0, -0.5], [0.0, 1.0, -0.5], [0.0, 0.0, 1.0]])  # COLMAP -> OpenCV pixels
    scaled = []
    for im in (ima, imb):
        K, D = _dist_coeffs(im.camera)
        s = min(1.0, conf["width"] / im.camera.width)
        size = (int(round(im.camera.width * s)), int(round(im.camera.height * s)))
        scaled.append((to_cv @ np.diag([s, s, 1.0]) @ K, D, size))
    (Ka, Da, size), (Kb, Db, size_b) = scaled
    pa, pb = Pose.of_image(ima), Pose.of_image(imb)
    # cameras turned half a turn against each other (flight lines flown both ways): the second image is
    # turned back first, else the rectification mirrors them (a negative focal length)
    turn = float(pa.R[0] @ pb.R[0]) < 0
    if turn:
        F = np.diag([-1.0, -1.0, 1.0])
        pb = Pose(F @ pb.R, F @ pb.t)
        Kb = Kb.copy()
        Kb[0, 2], Kb[1, 2] = size_b[0] - 1 - Kb[0, 2], size_b[1] - 1 - Kb[1, 2]
        Db = Db * np.array([1.0, 1.0, -1.0, -1.0, 1.0])  # tangential terms change sign
    R = pb.R @ pa.R.T
    T = pb.t - R @ pa.t
    R1, R2, P1, P2, _, _, _ = cv2.stereoRectify(
        Ka, Da, Kb, Db, size, R, T.reshape(3, 1), flags=cv2.CALIB_ZERO_DISPARITY, alpha=0
    )
    if not 0.25 <= P1[0, 0] / Ka[0, 0] <= 4.0:  # a rectification that blows the images up: degenerate
        return None
    rng = _disparity_range(rec, ima, imb, pa, pb, (R1, R2, P1, P2))
    if rng is None:
        return None
    axis, min_d, num = rng
    if num > conf["max_disparities"]:
        return None
    imgs = []
    for im, K, D, Rr, P, sz, rot in ((ima, Ka, Da, R1, P1, size, False), (imb, Kb, Db, R2, P2, size_b, turn)):
        grey = cv2.imread(str(image_dir / im.name), cv2.IMREAD_GRAYSCALE)
        if grey is None:
            raise FileNotFoundError(f"stereo: source image {image_dir / im.name} is missing")
        grey = cv2.resize(grey, sz, interpolation=cv2.INTER_AREA)
        if rot:
            grey = cv2.rotate(grey, cv2.ROTATE_180)
        m1, m2 = cv2.initUndistortRectifyMap(K, D, Rr, P, size, cv2.CV_32FC1)
        rect = cv2.remap(grey, m1, m2, cv2.INTER_LINEAR)
        imgs.append(np.ascontiguousarray(rect.T) if axis == 1 else rect)
    # the second image shifted by the smallest disparity: SGBM searches [0, num) and leaves a band of
    # only num pixels unmatched at the left border
    h, w = imgs[1].shape
    imgs[1] = cv2.warpAffine(imgs[1], np.float32([[1, 0, min_d], [0, 1, 0]]), (w, h))
    raw = _sgbm(conf, num).compute(imgs[0], imgs[1])
    if axis == 1:
        raw = np.ascontiguousarray(raw.T)
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = -P2[axis, 3] / (raw.astype(np.float32) / 16.0 + min_d)  # P2[axis, 3]: f * baseline
    ok = (raw >= 0) & np.isfinite(depth) & (depth > 0) & (depth < conf["max_depth_m"])
    depth = np.where(ok, depth, 0.0).astype(np.float32)
    Rt = np.c_[R1 @ pa.R, R1 @ pa.t]
    return depth, np.linalg.inv(to_cv) @ P1[:3, :3], Rt


def _fuse(frames: list[tuple[np.ndarray, np.ndarray, np.ndarray]], c: dict, capacity: int):
    """The TSDF mesh (open3d.t TriangleMesh) of (depth, K, [R | t]) frames, or None when its voxel
    blocks outgrow `capacity`."""
    import open3d as o3d
    import open3d.core as o3c

    vbg = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight"),
        attr_dtypes=(o3c.float32, o3c.float32),
        attr_channels=((1), (1)),
        voxel_size=float(c["voxel_m"]),
        block_resolution=8,
        block_count=capacity,
        device=o3c.Device("CPU:0"),
    )
    trunc = float(c["sdf_trunc_m"]) / float(c["voxel_m"])
    for depth, K, Rt in frames:
        s = float(c["fuse_width"]) / depth.shape[1]
        if s < 1.0:  # a voxel spans pixels of this width (and larger maps overflow open3d's frustum map)
            size = (int(c["fuse_width"]), int(round(depth.shape[0] * s)))
            depth = cv2.resize(depth, size, interpolation=cv2.INTER_NEAREST)
            K = np.diag([s, s, 1.0]) @ K
        img = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(depth)))
        Kt = o3c.Tensor(np.array([[K[0, 0], 0, K[0, 2] - 0.5], [0, K[1, 1], K[1, 2] - 0.5], [0, 0, 1]]))
        Et = o3c.Tensor(np.r_[Rt, [[0.0, 0.0, 0.0, 1.0]]])
        blocks = vbg.compute_unique_block_coordinates(img, Kt, Et, 1.0, c["max_depth_m"], trunc)
        if vbg.hashmap().size() + len(blocks) > 0.95 * capacity:
            logger.info("stereo: %d voxel blocks are not enough; again with twice as many", capacity)
            return None
        vbg.integrate(blocks, img, Kt, Et, 1.0, c["max_depth_m"], trunc)
    # open3d's own estimate of the vertex count falls short on large meshes (a crash); a vertex lies on
    # an edge of a voxel near the surface (|tsdf| < 1, weight above the threshold): at most 3 per voxel
    w = float(c["min_weight"])
    near = (np.abs(vbg.attribute("tsdf").numpy()) < 1.0) & (vbg.attribute("weight").numpy() >= w)
    return vbg.extract_triangle_mesh(weight_threshold=w, estimated_vertex_number=3 * int(near.sum()) + 1024)


class StereoSurface:
    """The TSDF mesh of the aerial images' pairwise stereo depth, ray cast at any camera."""

    def __init__(self, mesh, conf: dict):
        """`mesh`: an open3d.t.geometry.TriangleMesh."""
        import open3d as o3d

        self.conf = conf
        self.mesh = mesh
        self._scene: o3d.t.geometry.RaycastingScene | None = None  # built at the first depth()

    @classmethod
    def build(
        cls,
        model: str | Path | pycolmap.Reconstruction,
        image_dir: str | Path,
        conf: dict | None = None,
        progress: Callable[[float, str], None] | None = None,
    ) -> StereoSurface:
        """Match every pair of `stereo_pairs` and fuse their depth maps (see the module's docstring)."""
        c = {**confs["default"], **(conf or {})}
        rec = model if isinstance(model, pycolmap.Reconstruction) else pycolmap.Reconstruction(str(model))
        t0 = time.perf_counter()
        pairs = stereo_pairs(rec, c)
        frames = []
        for k, (a, b, _) in enumerate(pairs):
            out = pair_depth(rec, a, b, Path(image_dir), c)
            if out is not None:
                frames.append(out)
            if progress is not None:
                progress((k + 1) / len(pairs), f"stereo pair {k + 1}/{len(pairs)}")
        if not frames:
            raise ValueError("stereo: no pair of aerial images could be matched (too few shared points)")
        capacity = int(c["block_count"])
        mesh = None
        while mesh is None:  # the voxel hash map does not grow: start over with twice its capacity
            mesh = _fuse(frames, c, capacity)
            capacity *= 2
        logger.info(
            "stereo surface: %d of %d pairs fused, %d triangles, %.0f s",
            len(frames),
            len(pairs),
            len(mesh.triangle.indices),
            time.perf_counter() - t0,
        )
        return cls(mesh, c)

    @classmethod
    def cached(
        cls, model_dir: str | Path, image_dir: str | Path, conf: dict | None, cache_dir: str | Path
    ) -> StereoSurface:
        """The surface of `build`, read from cache_dir when built there before from the same model
        (its images.bin and points3D.bin) and conf; else built and written there (a PLY mesh)."""
        import open3d as o3d

        c = {**confs["default"], **(conf or {})}
        model_dir, cache_dir = Path(model_dir), Path(cache_dir)
        key = hashlib.sha256(json.dumps(c, sort_keys=True).encode())
        for f in ("images.bin", "points3D.bin"):
            key.update(sha256_file(model_dir / f).encode())
        path = cache_dir / f"surface-{key.hexdigest()[:16]}.ply"
        if path.is_file():
            mesh = o3d.t.io.read_triangle_mesh(str(path))
            if len(mesh.triangle.indices):
                logger.info("stereo surface read from %s", path)
                return cls(mesh, c)
        surface = cls.build(model_dir, image_dir, c)
        cache_dir.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp.ply")
        o3d.t.io.write_triangle_mesh(str(tmp), surface.mesh)
        tmp.replace(path)
        return surface

    def points(self, voxel_m: float, max_tilt_deg: float | None = None) -> np.ndarray:
        """The surface's vertices, one (their mean) per voxel of voxel_m metres: (N, 3); with max_tilt_deg
        only those of walls (a vertex normal within max_tilt_deg of horizontal; z is up)."""
        used = np.unique(self.mesh.triangle.indices.numpy().ravel())
        V = self.mesh.vertex.positions.numpy()[used]  # float32; the TSDF's buffer holds unused ones too
        if max_tilt_deg is not None:
            if "normals" not in self.mesh.vertex:
                self.mesh.compute_vertex_normals()
            nz = self.mesh.vertex.normals.numpy()[used, 2]
            V = V[np.abs(nz) < np.sin(np.radians(float(max_tilt_deg)))]
        if not len(V):
            return np.zeros((0, 3))
        return voxel_means(V, voxel_m)

    def depth(self, camera: Camera, pose: Pose) -> np.ndarray:
        """z-depth (H, W) of the surface at a camera, 0 where a ray hits nothing."""
        import open3d as o3d

        K = camera.K
        H, W = camera.height, camera.width
        u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
        xy = (np.stack([u.ravel(), v.ravel()], 1) - K[:2, 2]) / np.diag(K)[:2]
        d_world = np.c_[xy, np.ones(len(xy))] @ pose.R  # R^T d: rays of unit z-depth
        o = np.broadcast_to(pose.center, d_world.shape)
        rays = o3d.core.Tensor(np.c_[o, d_world].astype(np.float32))
        if self._scene is None:
            self._scene = o3d.t.geometry.RaycastingScene()
            self._scene.add_triangles(self.mesh)
        t = self._scene.cast_rays(rays)["t_hit"].numpy()  # in units of the ray's direction: z-depth
        t[~np.isfinite(t)] = 0.0
        return t.reshape(H, W).astype(np.float32)
