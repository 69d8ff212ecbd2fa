"""The synthetic survey (services.synth) on the `tiny` preset: files, determinism, ground truth, POS noise."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest
import typer
from typer.testing import CliRunner

from cli.synth import synth
from services.colmap_model import Camera, Pose, read_cameras_json, read_model
from services.pos import LocalFrame, read_pos_csv
from services.synth import confs, load_gt, main, read_covisible, read_depth

TINY = confs["tiny"]
N_AERIAL = 5 * TINY["aerial"]["grid"][0] * TINY["aerial"]["grid"][1]
N_GROUND = TINY["ground"]["count"]


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    return main(TINY, tmp_path_factory.mktemp("tiny"), seed=0)


def digests(scene: Path) -> dict[str, str]:
    """sha256 of every file of a scene folder, by relative path."""
    return {
        str(p.relative_to(scene)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(scene.rglob("*"))
        if p.is_file()
    }


def image_names(scene: Path) -> list[str]:
    return sorted(f"{s}/{p.name}" for s in ("aerial", "ground") for p in (scene / "images" / s).glob("*.jpg"))


def test_files_and_image_sizes(tiny):
    names = image_names(tiny)
    assert sum(n.startswith("aerial/") for n in names) == N_AERIAL
    assert sum(n.startswith("ground/") for n in names) == N_GROUND
    assert names[0] == "aerial/A0001.jpg" and names[-1] == f"ground/G{N_GROUND:04d}.jpg"
    for f in ("pos.csv", "cameras.json", "gt/depth.h5", "gt/covisible.csv", "gt/scene.json", "gt/sparse"):
        assert (tiny / f).exists(), f
    cams = read_cameras_json(tiny / "cameras.json")
    assert set(cams) == {"aerial", "ground"}
    for s in ("aerial", "ground"):
        assert (cams[s].width, cams[s].height) == (TINY[s]["width"], TINY[s]["height"])
    with h5py.File(tiny / "gt" / "depth.h5") as h5:
        assert sorted(k.replace("|", "/") for k in h5) == names
    for n in names:
        img = cv2.imread(str(tiny / "images" / n))
        cam = cams[n.split("/")[0]]
        assert img.shape == (cam.height, cam.width, 3), n
        assert img.std() > 10, f"{n} looks blank"
        depth = read_depth(tiny, n)
        assert depth.shape == (cam.height, cam.width) and depth.dtype == np.float32
        assert (depth > 0).mean() > 0.3 and np.isfinite(depth).all() and depth.min() >= 0
    meta = json.loads((tiny / "gt" / "scene.json").read_text())
    assert meta["preset"] == "tiny" and meta["seed"] == 0
    assert meta["counts"]["aerial"] == N_AERIAL and meta["counts"]["ground"] == N_GROUND


def test_deterministic_by_seed(tiny, tmp_path):
    again = main(TINY, tmp_path / "again", seed=0)
    assert digests(again) == digests(tiny)  # every file, byte for byte
    other = main(TINY, tmp_path / "other", seed=1)
    d0, d1 = digests(tiny), digests(other)
    assert d0["pos.csv"] != d1["pos.csv"]
    assert sum(d0[k] != d1[k] for k in d0 if k.startswith("images/")) == N_AERIAL + N_GROUND


def test_refuses_a_non_empty_folder(tiny):
    with pytest.raises(FileExistsError):
        main(TINY, tiny, seed=0)


def lookup_depth_bilinear(depth: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Depth at COLMAP pixels uv (N, 2) by bilinear interpolation of 1/depth (exact on a plane) where the
    4 neighbouring pixel centres see one continuous surface; nan elsewhere."""
    h, w = depth.shape
    u, v = uv[:, 0] - 0.5, uv[:, 1] - 0.5
    j0, i0 = np.floor(u).astype(int), np.floor(v).astype(int)
    ok = (j0 >= 0) & (i0 >= 0) & (j0 < w - 1) & (i0 < h - 1)
    j0, i0 = np.clip(j0, 0, w - 2), np.clip(i0, 0, h - 2)
    q = np.stack([depth[i0, j0], depth[i0, j0 + 1], depth[i0 + 1, j0], depth[i0 + 1, j0 + 1]], 1)
    q = q.astype(np.float64)
    ok &= (q.min(1) > 0) & (q.max(1) <= 1.02 * q.min(1))
    fu, fv = (u - j0)[:, None], (v - i0)[:, None]
    wts = np.concatenate([(1 - fu) * (1 - fv), fu * (1 - fv), (1 - fu) * fv, fu * fv], 1)
    inv = (wts / np.where(q > 0, q, 1.0)).sum(1)
    return np.where(ok, 1.0 / np.maximum(inv, 1e-12), np.nan)


def reprojection_check(gt, a: str, b: str) -> tuple[int, float, float]:
    """Points of view a (depth map) projected into view b: (number inside b on a continuous surface,
    fraction whose depth agrees with b's depth map within 1%, fraction that b would see through)."""
    da = gt.depth(a)
    ii, jj = np.mgrid[2 : da.shape[0] - 2 : 3, 2 : da.shape[1] - 2 : 3]
    d = da[ii, jj].astype(float)
    keep = (d > 0) & (d < 150)
    uv_a = np.stack([jj[keep] + 0.5, ii[keep] + 0.5], 1)
    X = gt.poses[a].unproject(gt.cameras[a].K, uv_a, d[keep])
    uv_b, z = gt.poses[b].project(gt.cameras[b].K, X)
    zb = lookup_depth_bilinear(gt.depth(b), uv_b)
    m = (z > 0) & np.isfinite(zb)
    rel = (zb[m] - z[m]) / z[m]
    return int(m.sum()), float((np.abs(rel) < 0.01).mean()), float((rel > 0.01).mean())


def test_ground_truth_depth_is_consistent_between_views(tiny):
    gt = load_gt(tiny)
    cov = sorted(gt.covisible, key=lambda r: -r[2])
    assert cov, "no co-visible aerial-ground pair"
    nadirs = [v["name"] for v in gt.meta["views"] if v["kind"] == "nadir"]
    # (a, b, least fraction of a's points that b sees: the rest is occluded in b)
    pairs = [(nadirs[0], nadirs[1], 0.5), (cov[0][1], cov[0][0], 0.3), (cov[-1][1], cov[-1][0], 0.03)]
    pairs += [(cov[0][0], cov[0][1], 0.03)]  # aerial -> ground: most of it is hidden from the street
    for a, b, least in pairs:
        n, agree, see_through = reprojection_check(gt, a, b)
        assert n > 200, (a, b, n)
        assert agree > least, (a, b, agree)
        assert see_through < 0.01, (a, b, see_through)  # b never sees a surface behind a's surface


def test_ground_truth_model_and_api(tiny):
    gt = load_gt(tiny)
    names = image_names(tiny)
    assert gt.names() == names and len(gt.names("ground")) == N_GROUND
    cams, poses = read_model(tiny / "gt" / "sparse")
    assert sorted(poses) == names
    centers = {v["name"]: np.array(v["center"]) for v in gt.meta["views"]}
    for n in names:
        assert np.allclose(poses[n].center, centers[n], atol=1e-4)
        assert np.allclose(poses[n].R @ poses[n].R.T, np.eye(3), atol=1e-9)
        assert isinstance(gt.cameras[n], Camera) and gt.cameras[n].model == "PINHOLE"
    # the true surface points lie where the depth maps say
    xyz, rgb = gt.points()
    assert len(xyz) >= 0.9 * TINY["gt"]["n_points"] and rgb.dtype == np.uint8
    a = names[0]
    uv, z = gt.poses[a].project(gt.cameras[a].K, xyz)
    zb = lookup_depth_bilinear(gt.depth(a), uv)
    ok = (z > 0) & np.isfinite(zb)
    assert ok.sum() > 50
    assert ((zb[ok] - z[ok]) / z[ok] > -0.01).mean() > 0.5  # visible or occluded, never behind the surface
    assert ((zb[ok] - z[ok]) / z[ok] < 0.01).mean() > 0.99  # (except sub-pixel thin things: lamp poles)


def test_covisible_pairs(tiny):
    rows = read_covisible(tiny)
    assert len(rows) > 0
    assert rows == sorted(rows)
    names = set(image_names(tiny))
    for a, g, ov in rows:
        assert a.startswith("aerial/") and g.startswith("ground/") and {a, g} <= names
        assert TINY["gt"]["covis_min"] <= ov <= 1.0


def test_pos_noise_matches_stated_sigmas(tiny):
    gt = load_gt(tiny)
    records = read_pos_csv(tiny / "pos.csv")
    assert sorted(r.name for r in records) == image_names(tiny)
    frame = LocalFrame(**TINY["origin"])
    nxy, nz, natt = [], [], []
    for r in records:
        sigma = TINY["pos"][r.image_set]
        assert (r.std_xy, r.std_z, r.std_att) == (sigma["std_xy"], sigma["std_z"], sigma["std_att"])
        e = frame.from_wgs84(r.lat, r.lon, r.h)[0] - gt.poses[r.name].center
        nxy += list(e[:2] / r.std_xy)
        nz.append(e[2] / r.std_z)
        R_true = gt.poses[r.name].R.T
        angle = np.degrees(np.arccos(np.clip((np.trace(R_true.T @ r.R_world_from_cam) - 1) / 2, -1, 1)))
        natt.append(angle / (r.std_att * np.sqrt(3)))  # per-axis sigma: E[angle^2] = 3 sigma^2
    nxy, nz, natt = map(np.asarray, (nxy, nz, natt))
    assert np.abs(nxy).max() < 5 and np.abs(nz).max() < 5 and natt.max() < 3
    assert 0.4 < np.sqrt(np.mean(nxy**2)) < 1.8
    assert 0.3 < np.sqrt(np.mean(nz**2)) < 2.2
    assert 0.4 < np.sqrt(np.mean(natt**2)) < 1.8
    assert np.abs(nxy).max() > 0.1  # not the truth


def test_photo_textures_change_only_the_colours(tiny, tmp_path):
    photos = tmp_path / "photos"
    photos.mkdir()
    rng = np.random.default_rng(0)
    for k in range(2):
        small = rng.integers(0, 255, (24, 32, 3), dtype=np.uint8)
        img = cv2.resize(small, (256, 192), interpolation=cv2.INTER_CUBIC)
        cv2.imwrite(str(photos / f"{k}.png"), img)
    out = main(TINY, tmp_path / "photo", seed=0, textures_dir=photos, supersample=1)
    names = image_names(tiny)
    assert image_names(out) == names
    assert all(np.array_equal(read_depth(out, n), read_depth(tiny, n)) for n in names)
    g = names[-1]
    assert not np.array_equal(cv2.imread(str(out / "images" / g)), cv2.imread(str(tiny / "images" / g)))


def test_cli_rejects_bad_input(tiny, tmp_path):
    app = typer.Typer()
    app.command()(synth)
    runner = CliRunner()
    r = runner.invoke(app, [str(tmp_path / "a"), "--preset", "huge"])
    assert r.exit_code == 2 and "unknown preset" in r.output
    r = runner.invoke(app, [str(tmp_path / "b"), "--preset", "tiny", "--textures", str(tmp_path / "none")])
    assert r.exit_code == 2 and "does not exist" in r.output
    r = runner.invoke(app, [str(tiny), "--preset", "tiny"])
    assert r.exit_code == 2 and "not empty" in r.output
    r = runner.invoke(app, [str(tmp_path / "c"), "--preset", "tiny", "--set", "scene.walls=0"])
    assert r.exit_code == 2 and "unknown key 'walls'" in r.output
    r = runner.invoke(app, [str(tmp_path / "c"), "--preset", "tiny", "--set", "scene.relief=deep"])
    assert r.exit_code == 2 and "--set" in r.output
    assert not any((tmp_path / d).exists() for d in "abc")


def test_pose_helpers_agree_with_depth(tiny):
    """Pixel centre (j + 0.5, i + 0.5) with depth d unprojects to a point that projects back to it."""
    gt = load_gt(tiny)
    n = gt.names("ground")[0]
    d = gt.depth(n)
    i, j = np.argwhere(d > 0)[len(np.argwhere(d > 0)) // 2]
    pose: Pose = gt.poses[n]
    K = gt.cameras[n].K
    X = pose.unproject(K, np.array([[j + 0.5, i + 0.5]]), np.array([float(d[i, j])]))
    uv, z = pose.project(K, X)
    assert np.allclose(uv, [[j + 0.5, i + 0.5]], atol=1e-6) and np.isclose(z[0], d[i, j], rtol=1e-6)


def test_walk_layout_takes_ground_images_in_sequence():
    """small-walk: 40 ground images 4 m apart one after the other (jumps only round a block's corner),
    each at the same offset from the kerb give or take 0.5 m, looking at the facades or along the street."""
    from services.synth.cameras import ground_views
    from services.synth.scene import make_scene

    conf = confs["small-walk"]
    rng = np.random.default_rng(0)
    scene = make_scene(conf["scene"], rng)
    views = ground_views(conf["ground"], scene, rng)
    assert len(views) == 40
    steps = np.linalg.norm(np.diff(np.array([v.C[:2] for v in views]), axis=0), axis=1)
    assert np.median(steps) == pytest.approx(4.0, abs=0.5)
    assert (steps > 6.0).sum() <= 3  # the walk turns at most three corners of the block
    assert {v.kind for v in views} <= {"in", "diag", "along"}
    spread = confs["small"]["ground"]
    assert "layout" not in spread  # the other presets keep their cameras spread round the blocks


def _one_building(relief: float):
    """A scene of one 20 x 10 x 12 m building (bays of 3 m, floors of 3 m over a 4 m ground floor) with
    openings recessed `relief` m, and its grid."""
    from services.synth.materials import (
        MAT_BUILDING,
        NPAR,
        P_BAY,
        P_DOOR,
        P_FLOOR,
        P_GFLOOR,
        P_PARAPET,
        P_PHOTO,
        P_RELIEF,
        P_SEED,
        P_WINH,
        P_WINW,
    )  # fmt: skip
    from services.synth.scene import Scene

    par = np.zeros(NPAR)
    par[:3] = 0.6
    values = {P_FLOOR: 3.0, P_GFLOOR: 4.0, P_BAY: 3.0, P_WINW: 0.5, P_WINH: 0.5, P_PARAPET: 0.5}
    for k, v in {**values, P_DOOR: 0.99, P_SEED: 5, P_PHOTO: -1.0, P_RELIEF: relief}.items():
        par[k] = v
    scene = Scene(
        np.array([[0.0, 0.0, 0.0, 20.0, 10.0, 12.0]]), np.array([MAT_BUILDING]), par[None], np.array([-1]),
        np.zeros((0, 4)), np.zeros(0, np.int64), np.zeros((0, NPAR)), np.zeros(0, np.int64),
        np.zeros((1, 1), np.int64), np.zeros(8), np.zeros(8), np.zeros(4),
    )  # fmt: skip
    return scene, scene.grid()


def test_recessed_openings_have_depth_reveals_and_shade():
    """A ray through a window's middle goes `relief` deeper than one on the wall beside it; one that
    enters the opening at 45 degrees near its edge stops on the jamb, whose normal faces it; the sun
    straight in front lights the glass, a sun low from the side leaves it in the jamb's shadow."""
    from services.synth import kernels as K

    scene, (gmeta, cstart, citems) = _one_building(0.25)
    args = (scene.boxes, scene.bmat, scene.bpar, scene.sph, gmeta, cstart, citems)
    # bay 0 of the -y facade: u (= x) in 1.75..3.25 on the first floor (z 4.85..6.35)
    glass = K.trace_camera(2.5, -10.0, 5.6, 0.0, 1.0, 0.0, *args)
    wall = K.trace_camera(4.0, -10.0, 5.6, 0.0, 1.0, 0.0, *args)
    assert wall[0] == pytest.approx(10.0) and wall[4] == 0
    assert glass[0] == pytest.approx(10.25) and glass[4] == 1 and glass[3] == 2
    s = 1 / np.sqrt(2)
    jamb = K.trace_camera(3.1 - 10.0, -10.0, 5.6, s, s, 0.0, *args)
    assert jamb[4] == 2 and jamb[5] == 0  # the jamb at u1 faces -x, against the ray
    assert jamb[0] * s == pytest.approx(10.15)
    box, par = scene.boxes[0], scene.bpar[0]
    assert K.out_of_recess(2.5, 0.25, 5.6, 2, box, par, 0.0, -1.0, 0.0)  # the sun in front
    low = np.array([0.95, -0.25, 0.1])
    assert not K.out_of_recess(2.5, 0.25, 5.6, 2, box, par, *(low / np.linalg.norm(low)))
    flat, (gm, cs, ci) = _one_building(0.0)
    assert K.trace_camera(
        2.5, -10.0, 5.6, 0.0, 1.0, 0.0, flat.boxes, flat.bmat, flat.bpar, flat.sph, gm, cs, ci
    )[0] == pytest.approx(10.0)


def test_wall_atlas_cuts_the_crops_at_their_scale(tmp_path):
    """The wall photos are the crops' pixels (their boxes, not whole photos), mip-mapped; a missing
    photo is an error that names it."""
    from services.synth.walls import LEVELS, WALL_CROPS, wall_atlas

    rng = np.random.default_rng(1)
    photos = {}
    for name in {c["photo"] for c in WALL_CROPS}:
        photos[name] = rng.integers(0, 255, (768, 1024, 3), dtype=np.uint8)
        cv2.imwrite(str(tmp_path / name.replace(".jpg", ".png")), photos[name])
    with pytest.raises(FileNotFoundError, match="26.jpg"):
        wall_atlas(tmp_path)
    for name, img in photos.items():
        cv2.imwrite(str(tmp_path / name), img, [cv2.IMWRITE_JPEG_QUALITY, 100])
    atlas, aoff, adim, m_per_px = wall_atlas(tmp_path)
    assert aoff.shape == (len(WALL_CROPS), LEVELS) and list(m_per_px) == [c["m_per_px"] for c in WALL_CROPS]
    for k, c in enumerate(WALL_CROPS):
        x0, y0, x1, y1 = c["box"]
        assert tuple(adim[k, 0]) == (y1 - y0, x1 - x0) and tuple(adim[k, 1]) == (
            (y1 - y0) // 2,
            (x1 - x0) // 2,
        )
        crop = atlas[aoff[k, 0] : aoff[k, 0] + (y1 - y0) * (x1 - x0) * 3].reshape(y1 - y0, x1 - x0, 3)
        whole = cv2.cvtColor(cv2.imread(str(tmp_path / c["photo"])), cv2.COLOR_BGR2RGB)
        assert np.array_equal(crop, whole[y0:y1, x0:x1])


def test_transient_cars_are_there_in_one_capture_only():
    """With a transient share, some parked cars are in the aerial capture's scene only and others in the
    ground's; the layout is the same as without them, and a scene without any is its own capture."""
    import copy

    from services.synth.scene import make_scene

    conf = copy.deepcopy(confs["small"]["scene"])
    plain = make_scene(conf, np.random.default_rng(4))
    assert plain.transient == {} and plain.for_capture("ground") is plain
    conf["transient"] = 0.5
    scene = make_scene(conf, np.random.default_rng(4))
    assert np.array_equal(scene.boxes, plain.boxes)
    kinds = set(scene.transient.values())
    assert kinds == {"aerial", "ground"}, scene.transient
    aerial, ground = scene.for_capture("aerial"), scene.for_capture("ground")
    only_ground = [g for g, c in scene.transient.items() if c == "ground"]
    only_aerial = [g for g, c in scene.transient.items() if c == "aerial"]
    assert not np.isin(aerial.bgroup, only_ground).any() and np.isin(aerial.bgroup, only_aerial).any()
    assert not np.isin(ground.bgroup, only_aerial).any() and np.isin(ground.bgroup, only_ground).any()
    assert len(aerial.boxes) < len(scene.boxes) and len(ground.boxes) < len(scene.boxes)


def test_isprs_walk_walks_the_isprs_block_and_renders_the_same_bytes_for_the_same_seed():
    """isprs-walk: isprs's scene and flight with 50 ground images 3.5 m apart in sequence; a ground image
    rendered from two builds of the survey with the same seed is the same array, another seed's is not."""
    from services.colmap_model import Camera
    from services.synth.pipeline import Renderer, build_survey, light_array

    walk, isprs = confs["isprs-walk"], confs["isprs"]
    assert walk["scene"] == isprs["scene"] and walk["aerial"] == isprs["aerial"]
    assert walk["lighting"] == isprs["lighting"] and walk["pos"] == isprs["pos"]
    cam = Camera("PINHOLE", 256, 192, [187.5, 187.5, 128.0, 96.0])  # the ground camera at a quarter size
    light = light_array(walk["lighting"]["ground"])
    renders = []
    for seed in (0, 0, 1):
        photos, scene, aerial, ground, _ = build_survey(walk, seed, None)
        renders.append([Renderer(scene, photos, seed)(ground[k], cam, light, 1)[0] for k in (0, 24)])
    assert len(ground) == 50 and len(aerial) == 60
    steps = np.linalg.norm(np.diff(np.array([v.C[:2] for v in ground]), axis=0), axis=1)
    assert np.median(steps) == pytest.approx(3.5, abs=0.5)
    assert (steps > 6.0).sum() <= 4  # round the block's corners only
    assert all(np.array_equal(a, b) for a, b in zip(renders[0], renders[1], strict=True))
    assert not any(np.array_equal(a, b) for a, b in zip(renders[0], renders[2], strict=True))
