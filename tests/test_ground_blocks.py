"""services.sfm.combined.blocks: chains of ground images the mapper left out, placed as one block on
their ties to the aerial points."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap

from services.colmap_model import Camera, Pose
from services.geometry import look_at
from services.sfm.combined import CombinedDatabase, default_conf
from services.sfm.combined.blocks import block_pose, fit_block, ties_reason, unregistered_chains

CAM = Camera("PINHOLE", 1024, 768, [750.0, 750.0, 512.0, 384.0])
BC = default_conf["blocks"]


def _walk(n: int) -> dict[str, Pose]:
    """n ground cameras 3.5 m apart along a street, looking at a facade 10 m away."""
    return {
        f"ground/G{i:04d}.jpg": look_at(np.array([3.5 * i, 0.0, 1.6]), np.array([3.5 * i, 10.0, 3.0]))
        for i in range(n)
    }


def test_the_chains_are_the_unregistered_images_joined_by_verified_pairs():
    walk = _walk(7)
    names = sorted(walk)
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(CAM.to_pycolmap(1))
    for i, n in enumerate(names, start=1):
        im = pycolmap.Image(name=n, keypoints=np.zeros((0, 2)), camera_id=1, image_id=i)
        if i <= 2:  # G0000 and G0001 registered
            rec.add_image_with_trivial_frame(im, pycolmap.Rigid3d(pycolmap.Rotation3d(walk[n].R), walk[n].t))
        else:
            rec.add_image_with_trivial_frame(im)
    g = names
    pairs = {
        f"{g[1]} {g[2]}": {"accepted": True},  # a registered image does not join a chain
        f"{g[2]} {g[3]}": {"accepted": True},
        f"{g[3]} {g[4]}": {"accepted": True},
        f"{g[4]} {g[5]}": {"accepted": False},  # refused: not a link
        f"{g[5]} {g[6]}": {"accepted": True},
    }
    ids = {n: i for i, n in enumerate(names, start=1)}
    cdb = CombinedDatabase(Path("unused.db"), ids, {}, {}, {}, ground_pairs=pairs)
    assert unregistered_chains(rec, cdb, 3) == [[g[2], g[3], g[4]]]
    assert unregistered_chains(rec, cdb, 2) == [[g[2], g[3], g[4]], [g[5], g[6]]]


def test_a_block_is_placed_by_the_ties_of_two_of_its_images_not_of_one():
    """The similarity model_from_block comes back from ties with a third of them wrong; a block whose
    agreeing ties all come through one image is not placed (one image's matches can be a repeated
    facade shifted by a window)."""
    rng = np.random.default_rng(3)
    truth = pycolmap.Sim3d(
        2.5, pycolmap.Rotation3d(look_at(np.zeros(3), np.array([1.0, 2.0, 0.3])).R), [5.0, -3.0, 1.0]
    )
    Y = rng.uniform(-10, 10, (90, 3))
    X = np.array([truth * y for y in Y]) + rng.normal(0, 0.05, (90, 3))
    X[60:] += rng.uniform(2.0, 6.0, (30, 3))  # wrong ties
    who = ["ground/G0003.jpg"] * 45 + ["ground/G0004.jpg"] * 45
    sim, agree = fit_block(Y, X, BC)
    assert sim is not None and abs(sim.scale - 2.5) < 0.02
    assert agree[:60].mean() > 0.95 and agree[60:].sum() <= 2
    images = sorted({w for w, ok in zip(who, agree, strict=True) if ok})
    assert ties_reason((int(agree.sum()), len(Y)), images, BC) == ""
    assert "through 1 of its images" in ties_reason((40, 45), ["ground/G0003.jpg"], BC)
    assert "ties agree" in ties_reason((12, 40), images, BC)  # too few ties


def test_a_block_camera_sees_the_model_as_it_saw_the_block():
    """block_pose: a point of the block frame and its image in a block camera; the camera placed in the
    model's frame sees the point mapped by the similarity at the same pixel."""
    sim = pycolmap.Sim3d(
        0.8, pycolmap.Rotation3d(look_at(np.zeros(3), np.array([0.3, 1.0, -0.2])).R), [10.0, 4.0, -2.0]
    )
    pose = _walk(3)["ground/G0002.jpg"]
    im = pycolmap.Image(name="ground/G0002.jpg", keypoints=np.zeros((0, 2)), camera_id=1, image_id=1)
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(CAM.to_pycolmap(1))
    rec.add_image_with_trivial_frame(im, pycolmap.Rigid3d(pycolmap.Rotation3d(pose.R), pose.t))
    r = block_pose(rec.images[1], sim)
    placed = Pose(np.asarray(r["R"]), np.asarray(r["t"]))
    Xb = np.array([[7.0, 9.0, 2.0], [6.0, 11.0, 4.5]])
    uv_block, _ = pose.project(CAM.K, Xb)
    uv_model, _ = placed.project(CAM.K, np.array([sim * x for x in Xb]))
    assert np.allclose(uv_block, uv_model, atol=1e-6)
    assert np.allclose(placed.center, sim * pose.center)
