"""Aerial track completion (services/reduce/tracks.py) on constructed cameras, keypoints and descriptors."""

from __future__ import annotations

import numpy as np

from services.colmap_model import Camera
from services.geometry import look_at
from services.reduce.tracks import complete_tracks, guided_matches

CAM = Camera("PINHOLE", 400, 300, [350.0, 350.0, 200.0, 150.0])


def unit(v):
    v = np.asarray(v, np.float32)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def scene(n: int = 30, seed: int = 0):
    """Points on a facade seen by A (the observer), B (15 deg away), C (from behind the facade), with
    keypoints at every projection whose descriptors are the points' own (plus noise)."""
    rng = np.random.default_rng(seed)
    X = np.c_[rng.uniform(-5, 5, n), np.zeros(n), rng.uniform(0, 6, n)]
    poses = {
        "aerial/A.jpg": look_at(np.array([0.0, -40, 30]), np.array([0.0, 0, 3])),
        "aerial/B.jpg": look_at(np.array([11.0, -38, 30]), np.array([0.0, 0, 3])),
        "aerial/C.jpg": look_at(np.array([0.0, 40, 30]), np.array([0.0, 0, 3])),
    }
    desc = unit(rng.normal(size=(n, 64)))
    kps, descs = {}, {}
    for name, pose in poses.items():
        uv, _ = pose.project(CAM.K, X)
        kps[name] = (uv + rng.normal(scale=0.3, size=uv.shape)).astype(np.float32)
        descs[name] = unit(desc + rng.normal(scale=0.05, size=desc.shape))
    return X, poses, kps, descs


def test_points_gain_observations_where_they_are_seen():
    X, poses, kps, descs = scene()
    obs = [[("aerial/A.jpg", i, 0.9)] for i in range(len(X))]
    cams = {n: CAM for n in poses}
    out, stats = complete_tracks(None, X, obs, cams, poses, kps, descs)
    for i, items in enumerate(out):
        names = {a for a, _, _ in items}
        assert "aerial/B.jpg" in names  # similar viewpoint: found, at the right keypoint
        assert ("aerial/B.jpg", i) in {(a, k) for a, k, _ in items}
        assert "aerial/C.jpg" not in names  # the facade seen from behind: not sought
        assert ("aerial/A.jpg", i, 0.9) in items  # existing observations kept
        assert all(s <= 0.9 for _, _, s in items)
    assert stats["added"] == len(X)


def test_dissimilar_or_far_keypoints_are_not_taken():
    X, poses, kps, descs = scene()
    obs = [[("aerial/A.jpg", i, 0.9)] for i in range(len(X))]
    cams = {n: CAM for n in poses}
    other = dict(descs)
    other["aerial/B.jpg"] = unit(np.random.default_rng(5).normal(size=descs["aerial/B.jpg"].shape))
    out, stats = complete_tracks(None, X, obs, cams, poses, kps, other)
    assert stats["added"] == 0
    moved = dict(kps)
    moved["aerial/B.jpg"] = kps["aerial/B.jpg"] + [8.0, 0.0]  # beyond the 3 px radius
    _, stats = complete_tracks(None, X, obs, cams, poses, moved, descs)
    assert stats["added"] == 0
    _, stats = complete_tracks({"enabled": False}, X, obs, cams, poses, kps, descs)
    assert stats["added"] == 0


def test_guided_matches_one_to_one_and_ambiguity():
    d = unit(np.eye(4, dtype=np.float32))
    kp = np.array([[10.0, 10.0], [11.0, 10.0], [50.0, 50.0]], np.float32)
    kd = np.stack([d[0], d[1], d[2]])
    # two points projecting next to each other, both most like keypoint 0: it goes to the more similar
    uv = np.array([[10.2, 10.0], [10.4, 10.0], [50.0, 50.0]])
    pdesc = unit(np.stack([d[0] + 0.1 * d[1], d[0] + 0.3 * d[1], d[2]]))
    p, k, s = guided_matches(uv, pdesc, kp, kd, px=3.0, min_similarity=0.8, margin=0.05)
    assert list(zip(p.tolist(), k.tolist(), strict=True)) == [(0, 0), (2, 2)]
    # a point equally like two keypoints within the radius is ambiguous: not matched
    kd2 = np.stack([d[0], d[0], d[2]])
    p, k, _ = guided_matches(uv[:1], unit(d[:1]), kp, kd2, px=3.0, min_similarity=0.8, margin=0.05)
    assert len(p) == 0


def test_order_of_images_does_not_matter():
    X, poses, kps, descs = scene(seed=3)
    obs = [[("aerial/A.jpg", i, 0.9)] for i in range(len(X))]
    cams = {n: CAM for n in poses}
    a, _ = complete_tracks(None, X, obs, cams, poses, kps, descs)
    rev = dict(reversed(list(poses.items())))
    b, _ = complete_tracks(None, X, obs, cams, rev, kps, descs)
    assert a == b
