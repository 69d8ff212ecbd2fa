"""Ground images whose matches fit two poses alike (services.sfm.combined.ambiguity): a camera whose
matches are half a repeated facade shifted by a window holds two poses a window apart and is ambiguous; a
few such matches, or two poses at one place, are not."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest

from services.colmap_model import Camera, Pose
from services.geometry import look_at
from services.sfm import combined as combined_sfm
from services.sfm.combined.ambiguity import ambiguous_images, competing_poses, default_conf, hanging_images

CAM = Camera("PINHOLE", 1024, 768, [750.0, 750.0, 512.0, 384.0])
WINDOW = np.array([1.5, 0.0, 0.0])  # the facade repeats every 1.5 m along the street (x)


def _facade(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.stack([rng.uniform(-4, 12, n), 10.0 + rng.uniform(0, 0.5, n), rng.uniform(0, 8, n)], 1)


def _visible(pose: Pose, P: np.ndarray) -> np.ndarray:
    uv, z = pose.project(CAM.K, P)
    return (z > 0) & (uv >= 5).all(1) & (uv[:, 0] < CAM.width - 5) & (uv[:, 1] < CAM.height - 5)


def _matches(pose: Pose, n_true: int, n_shifted: int, shift: np.ndarray, seed: int = 0):
    """kp (N, 2) - X (N, 3): n_true points where the camera sees them, n_shifted matched to the point one
    `shift` along the facade from the one the pixel sees."""
    rng = np.random.default_rng(seed)
    P = _facade(4 * (n_true + n_shifted), seed)
    P = P[_visible(pose, P) & _visible(pose, P + shift)][: n_true + n_shifted]
    seen = P.copy()
    seen[n_true:] += shift  # the pixel sees the next window; its match is this one's point
    kp = pose.project(CAM.K, seen)[0] + rng.normal(0, 0.5, (len(P), 2))
    return kp, P


@pytest.mark.parametrize(
    ("n_shifted", "shift", "ambiguous"),
    [(40, WINDOW, True), (8, WINDOW, False), (40, 0.1 * WINDOW, False), (0, WINDOW, False)],
)
def test_half_a_repeated_facade_makes_two_poses(n_shifted, shift, ambiguous):
    pose = look_at(np.array([4.0, 0.0, 1.6]), np.array([4.0, 10.0, 3.0]))
    kp, X = _matches(pose, 50, n_shifted, shift)
    hyp = competing_poses(kp, X, CAM.to_pycolmap(1))
    assert hyp.first_inliers >= 50 - 3
    assert hyp.ambiguous(default_conf) is ambiguous
    if ambiguous:  # the second pose stands a window from the first
        assert hyp.separation_m == pytest.approx(np.linalg.norm(shift), abs=0.2)
        assert "two poses" in hyp.reason()


def test_ambiguous_images_reads_the_verified_matches_through_the_models_points(tmp_path):
    """Through a database and a model: the image matched to two neighbours' points (each seen by both),
    half of its matches a window off, is found ambiguous; with them all right it is not."""
    poses = {
        "ground/G0000.jpg": look_at(np.array([0.0, 0.0, 1.6]), np.array([2.0, 10.0, 3.0])),
        "ground/G0001.jpg": look_at(np.array([4.0, 0.0, 1.6]), np.array([4.0, 10.0, 3.0])),
        "ground/G0002.jpg": look_at(np.array([8.0, 0.0, 1.6]), np.array([6.0, 10.0, 3.0])),
    }
    for n_shifted, expected in ((45, True), (0, False)):
        root = tmp_path / str(n_shifted)
        root.mkdir()
        db = pycolmap.Database.open(str(root / "database.db"))
        ids = combined_sfm.write_ground(db, CAM, sorted(poses))
        a, c, b = (ids[n] for n in sorted(poses))  # the candidate between its two neighbours
        P = _facade(3000, 1)
        both = P[_visible(poses["ground/G0000.jpg"], P) & _visible(poses["ground/G0002.jpg"], P)]
        pc = poses["ground/G0001.jpg"]
        ok = _visible(pc, both) & _visible(pc, both + WINDOW)
        P = both[ok][: 50 + n_shifted]
        seen = P.copy()
        seen[50:] += WINDOW
        kp = {
            a: poses["ground/G0000.jpg"].project(CAM.K, P)[0],
            b: poses["ground/G0002.jpg"].project(CAM.K, P)[0],
            c: pc.project(CAM.K, seen)[0],
        }
        for i, k in kp.items():
            db.write_keypoints(i, k.astype(np.float32))
        idx = np.arange(len(P))
        combined_sfm.write_pair(db, c, a, np.stack([idx, idx], 1), None, True)
        db.close()
        rec = pycolmap.Reconstruction()
        rec.add_camera_with_trivial_rig(CAM.to_pycolmap(1))
        for name, i in ids.items():
            p = poses[name]
            im = pycolmap.Image(name=name, keypoints=kp[i], camera_id=1, image_id=i)
            rec.add_image_with_trivial_frame(im, pycolmap.Rigid3d(pycolmap.Rotation3d(p.R), p.t))
        for k in range(len(P)):
            track = pycolmap.Track([pycolmap.TrackElement(a, k), pycolmap.TrackElement(b, k)])
            rec.add_point3D(P[k], track, np.zeros(3, np.uint8))
        found = ambiguous_images(rec, [c], str(root / "database.db"), default_conf)
        assert (c in found) is expected
        assert ambiguous_images(rec, [c], str(root / "database.db"), {**default_conf, "enabled": False}) == {}


def test_an_image_all_of_whose_points_one_other_image_sees_hangs_on_it():
    """Three ground cameras along a facade: the third's points all seen by the second (one pair) hangs on
    it, unless a verified pair with the first checks them; with a tenth of its points the first's and not
    the second's it does not; an aerial image seeing the points is no ground support."""
    poses = [look_at(np.array([4.0 * i, 0.0, 1.6]), np.array([4.0 * i, 10.0, 3.0])) for i in range(3)]
    P = _facade(400, 2)
    P = P[_visible(poses[1], P) & _visible(poses[2], P) & _visible(poses[0], P)][:100]
    assert len(P) == 100

    def model(own: int) -> pycolmap.Reconstruction:
        """Images 1-3 (ground) and 4 (aerial); image 3's first `own` points seen by image 1, not 2."""
        rec = pycolmap.Reconstruction()
        rec.add_camera_with_trivial_rig(CAM.to_pycolmap(1))
        names = ["ground/G0.jpg", "ground/G1.jpg", "ground/G2.jpg", "aerial/A0.jpg"]
        for i, name in enumerate(names, 1):
            pose = (
                poses[i - 1] if i <= 3 else look_at(np.array([4.0, -20.0, 30.0]), np.array([4.0, 10.0, 3.0]))
            )
            kp = pose.project(CAM.K, P)[0]
            im = pycolmap.Image(name=name, keypoints=kp, camera_id=1, image_id=i)
            rec.add_image_with_trivial_frame(im, pycolmap.Rigid3d(pycolmap.Rotation3d(pose.R), pose.t))
        for k in range(len(P)):
            partner = 1 if k < own else 2
            elements = [
                pycolmap.TrackElement(3, k),
                pycolmap.TrackElement(partner, k),
                pycolmap.TrackElement(4, k),
            ]
            rec.add_point3D(P[k], pycolmap.Track(elements), np.zeros(3, np.uint8))
        return rec

    hung = hanging_images(model(0), [3], 0.95)
    assert list(hung) == [3] and "hangs on ground/G1.jpg: 100 of its 100 points" in hung[3]
    # its points all G1's too, but its pair with G0 checks them (a walk's next-but-one neighbour)
    walk = {"ground/G2.jpg": {"ground/G1.jpg", "ground/G0.jpg"}}
    assert hanging_images(model(0), [3], 0.95, walk) == {}
    assert list(hanging_images(model(0), [3], 0.95, {"ground/G2.jpg": {"ground/G1.jpg"}})) == [3]
    assert hanging_images(model(3), [3], 0.95) != {}  # 97 of 100: still one pair's
    assert hanging_images(model(10), [3], 0.95) == {}  # 90 of 100 with G1, 10 with G0: checked
