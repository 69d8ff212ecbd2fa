"""Export of a match file to a COLMAP database, and incremental mapping from it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap
import pytest

from services.colmap_db import export_to_database
from services.colmap_model import Camera, Pose
from shared.matchfile import MatchFile, PairMatches

CAMERAS = {
    "aerial": Camera("PINHOLE", 640, 480, [500.0, 500.0, 320.0, 240.0]),
    "ground": Camera("PINHOLE", 640, 480, [450.0, 450.0, 320.0, 240.0]),
}


def look_at(center, target) -> Pose:
    c, z = np.asarray(center, float), np.asarray(target, float) - center
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    return Pose.from_center(np.stack([x, np.cross(z, x), z], 1), c)


POSES = {
    "aerial/A1.jpg": look_at([-4.0, 0, 0], [0, 0, 20.0]),
    "aerial/A2.jpg": look_at([4.0, 0, 0], [0, 0, 20.0]),
    "ground/G1.jpg": look_at([0.0, 3, 1], [0, 0, 20.0]),
}


def planted_match_file(path: Path, n: int = 300, n_outliers: int = 0) -> Path:
    """Random 3D points seen by three cameras: exact keypoints (+0.3 px noise), identity matches."""
    rng = np.random.default_rng(0)
    X = rng.uniform([-5, -5, 18], [5, 5, 22], (n, 3))
    with MatchFile(path, "w", method="planted") as mf:
        for name, pose in POSES.items():
            cam = CAMERAS[name.split("/")[0]]
            uv, _ = pose.project(cam.K, X)
            uv = np.r_[uv + rng.normal(0, 0.3, uv.shape), rng.uniform(0, 480, (n_outliers, 2))]
            mf.add_keypoints(name, uv, (cam.width, cam.height))
        names = sorted(POSES)
        m = np.stack([np.arange(n + n_outliers)] * 2, 1)
        inliers = np.arange(n + n_outliers) < n
        for i in range(3):
            for j in range(i + 1, 3):
                # store one pair in reverse order (higher image id first) to exercise COLMAP's pair order
                pm = PairMatches(names[i], names[j], m, np.ones(len(m)), inliers)
                mf.add_pair(pm.swapped() if (i, j) == (0, 2) else pm)
    return path


def test_export_and_read_back(tmp_path):
    mfile = planted_match_file(tmp_path / "m.h5", n=50, n_outliers=10)
    db_path = tmp_path / "db" / "database.db"
    db_path.parent.mkdir()
    db_path.write_text("stale")  # replaced by a fresh database
    assert export_to_database(mfile, db_path, CAMERAS) == db_path
    db = pycolmap.Database.open(str(db_path))
    try:
        assert db.num_cameras() == 2 and db.num_rigs() == 2
        assert db.num_images() == 3 and db.num_frames() == 3
        images = {im.name: im for im in db.read_all_images()}
        assert {im.camera_id for im in images.values()} == {1, 2}
        assert all(im.frame_id == im.image_id for im in images.values())
        a1, a2, g1 = (images[n].image_id for n in sorted(POSES))
        with MatchFile(mfile) as mf:
            np.testing.assert_allclose(db.read_keypoints(g1), mf.keypoints("ground/G1.jpg"))
        cam = db.read_camera(images["ground/G1.jpg"].camera_id)
        assert cam.model.name == "PINHOLE" and list(cam.params) == CAMERAS["ground"].params
        assert db.num_matched_image_pairs() == 3 and db.num_verified_image_pairs() == 3
        for i, j in ((a1, a2), (a1, g1), (g1, a1), (a2, g1)):
            m = db.read_matches(i, j)
            np.testing.assert_array_equal(m, np.stack([np.arange(60)] * 2, 1))
            tvg = db.read_two_view_geometry(i, j)
            assert tvg.config == pycolmap.TwoViewGeometryConfiguration.UNCALIBRATED
            np.testing.assert_array_equal(tvg.inlier_matches, np.stack([np.arange(50)] * 2, 1))
    finally:
        db.close()

    export_to_database(mfile, db_path, CAMERAS, only_inliers=True)
    db = pycolmap.Database.open(str(db_path))
    try:
        assert db.num_images() == 3 and db.read_matches(1, 3).shape == (50, 2)
    finally:
        db.close()


def test_bad_cameras(tmp_path):
    mfile = planted_match_file(tmp_path / "m.h5", n=20)
    with pytest.raises(KeyError, match="ground"):
        export_to_database(mfile, tmp_path / "db.db", {"aerial": CAMERAS["aerial"]})
    small = {**CAMERAS, "ground": Camera("PINHOLE", 320, 240, [225.0, 225.0, 160.0, 120.0])}
    with pytest.raises(ValueError, match="image size"):
        export_to_database(mfile, tmp_path / "db.db", small)


def test_incremental_mapping_registers_planted_scene(tmp_path):
    mfile = planted_match_file(tmp_path / "m.h5", n=300, n_outliers=30)
    db_path = export_to_database(mfile, tmp_path / "database.db", CAMERAS)
    (tmp_path / "images").mkdir()  # the mapper checks that the folder exists; colours are not extracted
    opts = pycolmap.IncrementalPipelineOptions()
    opts.extract_colors = False
    opts.num_threads = 1
    recs = pycolmap.incremental_mapping(db_path, tmp_path / "images", tmp_path / "sparse", opts)
    assert len(recs) == 1
    rec = recs[0]
    assert rec.num_reg_images() == 3
    assert rec.num_points3D() >= 250
    assert {im.name for im in rec.images.values()} == set(POSES)
