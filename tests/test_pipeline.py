"""The pipeline (services/pipeline/) end to end on the `tiny` synthetic preset, with the ground-truth
renderer standing in for 3DGS (the 3DGS stages are tested in test_splat*.py), and its job folder
mechanics: markers, fingerprints, skipping and resuming.

The tiny preset is made a little less tiny (ground images of 480x360) and matched with SIFT, so that the
whole run takes about a minute on 2 cores; it is a test of the mechanics, not of the matching quality
(bench/method.py measures that on `small`)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from services import pipeline
from services.pipeline import DEFAULT_STAGES as STAGES
from shared.matchfile import MatchFile


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    import copy

    from services import synth

    conf = copy.deepcopy(synth.confs["tiny"])
    conf["ground"].update(width=480, height=360, f=351.0)
    out = tmp_path_factory.mktemp("tiny") / "scene"
    return synth.main(conf, out, seed=0)


@pytest.fixture(scope="module")
def tiny_job(tiny_scene, tmp_path_factory):
    root = tmp_path_factory.mktemp("job") / "job"
    job = pipeline.Job.create(
        root,
        tiny_scene / "images" / "aerial",
        tiny_scene / "images" / "ground",
        tiny_scene / "pos.csv",
        tiny_scene / "cameras.json",
        options={
            "view_planner": "ground-aware",
            "views_per_ground_image": 4,
            "matcher": "sift",
            "max_keypoints": 1024,
            "splat_steps": 100,  # the optional splat_all stage (test_splat_on_all_images)
            "splat_max_width": 160,
        },
        settings={
            "renderer": "gt",
            "scene": str(tiny_scene),
            "torch_threads": 1,
            "sfm": {"features": {"max_num_features": 2048}},
        },
    )
    events = []
    results = pipeline.run(job, progress=lambda s, f, m: events.append((s, f, m)))
    return job, results, events


def test_stages_complete_and_outputs_exist(tiny_job):
    job, results, events = tiny_job
    assert list(results) == list(STAGES)
    assert not any(r["skipped"] for r in results.values())
    for s in STAGES:
        assert pipeline.is_done(job, s)
        for p in pipeline.REGISTRY[s].outputs(job):
            assert p.exists(), p
    # progress: every stage starts at 0 and ends at 1
    for s in STAGES:
        fr = [f for st, f, _ in events if st == s]
        assert fr[0] == 0.0 and fr[-1] == 1.0 and all(0.0 <= f <= 1.0 for f in fr)
    assert pipeline.status(job) == {s: "done" for s in STAGES}


def test_matches_were_produced(tiny_job):
    job, _, _ = tiny_job
    views = json.loads((job.dir("views") / "views.json").read_text())["views"]
    assert len(views) >= 4 and all((job.dir("views") / v["image"]).is_file() for v in views)
    assert len({v["source"] for v in views}) >= 3  # views planned for (nearly) every ground image
    assert sorted(p.stem for p in job.dir("matches").glob("*.h5")) == sorted(v["name"] for v in views)
    n_render = 0
    for p in job.dir("matches").glob("*.h5"):
        with MatchFile(p) as mf:
            n_render += sum(int(pm.inliers.sum()) for pm in mf.iter_pairs())
    assert n_render > 100
    with MatchFile(job.dir("transfer") / "matches.h5") as mf:
        pairs = list(mf.iter_pairs())
        assert pairs and all(
            pm.name0.startswith("aerial/") and pm.name1.startswith("ground/") for pm in pairs
        )
        assert sum(len(pm.matches) for pm in pairs) > 0
        assert set(mf.views) <= {v["name"] for v in views}
    poses = json.loads((job.dir("transfer") / "ground_poses.json").read_text())["images"]
    assert set(poses) <= {f"ground/G000{i}.jpg" for i in range(1, 5)}
    rep = json.loads((job.dir("combined") / "report.json").read_text())
    assert rep["num_registered"]["aerial"] == rep["num_images"]["aerial"] == 20
    assert rep["num_images"]["ground"] == 4
    from services.sfm.combined.report import CAUSES

    assert set(poses) == {f"ground/G000{i}.jpg" for i in range(1, 5)}  # with or without correspondences
    assert all("views" in p and "view_aerial_fraction" in p for p in poses.values())
    out = {g: d for g, d in rep["ground"].items() if not d["registered"]}
    assert all(d["cause"] in CAUSES for d in out.values()), out  # every image left out says why
    assert sum(rep["causes"].values()) == len(out)


def test_every_localized_ground_image_is_in_the_combined_model(tiny_job):
    """A ground image the reducer localized (accepted PnP pose) is registered in the combined model: by
    the mapper, or added at its PnP pose when none of its pairs is strong enough for the mapper."""
    import numpy as np
    import pycolmap

    job, _, _ = tiny_job
    poses = json.loads((job.dir("transfer") / "ground_poses.json").read_text())["images"]
    rep = json.loads((job.dir("combined") / "report.json").read_text())
    rec = pycolmap.Reconstruction(str(job.dir("combined") / "sparse"))
    reg = {im.name: im for im in rec.images.values() if im.has_pose}
    for g, r in poses.items():
        if r["accepted"]:
            assert g in reg and rep["ground"][g]["registered"], g
    for g in rep["added_pnp_ground_images"]:
        assert rep["ground"][g]["registered_by"] == "pnp"
        assert np.allclose(reg[g].projection_center(), poses[g]["center"], atol=1e-6)
    assert rep["num_registered"]["ground"] == sum(n.startswith("ground/") for n in reg)


def test_localized_ground_images_survive_a_mapper_that_makes_no_model(tiny_job, tmp_path, monkeypatch):
    """When pycolmap's mapper returns no model, the combined model is the seeded input model with the
    localized ground images added at their PnP poses (not an error, not an empty result)."""
    import pycolmap

    job, _, _ = tiny_job
    monkeypatch.setattr(pycolmap, "incremental_mapping", lambda *a, **k: {})
    out = pipeline.combined_reconstruction(job, tmp_path / "combined")
    rep = json.loads((tmp_path / "combined" / "report.json").read_text())
    poses = json.loads((job.dir("transfer") / "ground_poses.json").read_text())["images"]
    accepted = {g for g, r in poses.items() if r["accepted"]}
    assert rep["num_registered"]["aerial"] == 20
    assert {g for g, d in rep["ground"].items() if d["registered"]} == accepted
    assert all(rep["ground"][g]["registered_by"] == "pnp" for g in accepted)
    assert pycolmap.Reconstruction(str(out)).num_reg_images() == 20 + len(accepted)


def test_ground_pairs_matched_ahead_are_not_matched_again(tiny_job, tmp_path, monkeypatch):
    """The demo's baselines' process matches the combined SfM's ground pairs ahead, from its own copy of
    the features, into the job's pair cache: the combined SfM then matches none of them again."""
    import shutil

    from services import matching
    from services.sfm.combined.pair_cache import pair_cache_path

    job, _, _ = tiny_job
    copy = shutil.copy2(job.features_path, tmp_path / job.features_path.name)
    cache = pair_cache_path(job.features_path, job.match_conf()["matcher"])
    kept = cache.rename(tmp_path / "kept.h5") if cache.exists() else None  # the combined stage's own
    try:
        n = pipeline.stages.match_ground_pairs_ahead(job, Path(copy))
        assert n > 0 and cache.is_file()
        calls = []
        real = matching.match_features
        monkeypatch.setattr(matching, "match_features", lambda *a: calls.append(a[2]) or real(*a))
        pipeline.combined_reconstruction(job, tmp_path / "combined")
        rep = json.loads((tmp_path / "combined" / "report.json").read_text())
        assert calls == [] and len(rep["ground_pairs"]) == n
    finally:
        cache.unlink(missing_ok=True)
        if kept is not None:
            kept.rename(cache)


def test_localized_ground_images_the_mapper_leaves_uncertain_are_kept_at_their_pnp_pose(tiny_job, tmp_path):
    """The mapper registers every ground image itself (none is held at its PnP pose: seed_pnp_poses
    off) and each is judged by the model's covariance; with a bound no pose meets, every one it placed
    is dropped, and those the reducer localized come back at their PnP pose, the others stay out."""
    import copy

    import numpy as np
    import pycolmap

    job, _, _ = tiny_job
    strict = pipeline.Job.load(job.root)
    strict.settings = copy.deepcopy(job.settings)
    strict.settings["combined"] = {
        **strict.settings.get("combined", {}),
        "max_position_std_m": 1e-9,
        "seed_pnp_poses": False,
    }
    out = pipeline.combined_reconstruction(strict, tmp_path / "combined")
    rep = json.loads((tmp_path / "combined" / "report.json").read_text())
    poses = json.loads((job.dir("transfer") / "ground_poses.json").read_text())["images"]
    accepted = {g for g, r in poses.items() if r["accepted"]}
    assert accepted, "the tiny scene's reducer localizes ground images"
    assert rep["seeded_ground_images"] == 0
    assert {g for g, d in rep["ground"].items() if d["registered"]} == accepted
    assert set(rep["added_pnp_ground_images"]) == accepted
    rec = pycolmap.Reconstruction(str(out))
    for g in accepted:
        assert np.allclose(rec.find_image_with_name(g).projection_center(), poses[g]["center"], atol=1e-6)
    for g, d in rep["ground"].items():
        if g not in accepted and "reason" in d and "dropped" in d["reason"]:
            assert "ill-determined" in d["reason"] or "POS" in d["reason"]


def test_the_reducer_counts_the_pnp_inliers_on_trusted_rendered_depth(tiny_job, tmp_path):
    """ground_poses.json says how many of a pose's inliers rest on rendered depth the reducer trusted
    (the tiny job renders exact views: all of them), what the combined reconstruction's default
    seed_pnp_poses ("trusted") decides on (tests/test_combined_checks.py)."""
    from services.sfm.combined import rests_on_trusted_depth

    job, _, _ = tiny_job
    conf = job.combined_conf()
    assert conf["seed_pnp_poses"] == "trusted"
    poses = json.loads((job.dir("transfer") / "ground_poses.json").read_text())["images"]
    accepted = {g: r for g, r in poses.items() if r["accepted"]}
    assert accepted
    views = {v["name"] for v in json.loads((job.dir("views") / "views.json").read_text())["views"]}
    for r in accepted.values():
        assert 0 < r["trusted_depth_inliers"] <= r["num_inliers"]
        assert rests_on_trusted_depth(r, conf)
        # and which rendered views its inliers came through, each inlier once
        assert set(r["inlier_views"]) <= views and sum(r["inlier_views"].values()) == r["num_inliers"]
    # a pose counts when at least half of its inliers (seed_min_trusted_ratio) are on trusted depth
    assert rests_on_trusted_depth({"num_inliers": 40, "trusted_depth_inliers": 20}, conf)
    assert not rests_on_trusted_depth({"num_inliers": 40, "trusted_depth_inliers": 19}, conf)
    assert not rests_on_trusted_depth({"num_inliers": 0, "trusted_depth_inliers": 0}, conf)
    assert not rests_on_trusted_depth({"num_inliers": 40}, conf)  # reducer output before this count
    # with the rendered depth unused, no inlier rests on it
    from services import reduce as transfer

    conf = {**job.transfer_conf(), "pnp": {**job.transfer_conf()["pnp"], "depth_points": False}}
    transfer.main(
        conf,
        job.dir("views") / "views.json",
        sorted(job.dir("matches").glob("*.h5")),
        job.dir("sfm") / "sparse",
        job.pos,
        job.cameras,
        job.dir("sfm") / "georef.json",
        tmp_path / "transfer",
        features=job.features_path,
    )
    poses = json.loads((tmp_path / "transfer" / "ground_poses.json").read_text())["images"]
    assert all(r.get("trusted_depth_inliers", 0) == 0 for r in poses.values())


def test_rerun_skips_every_stage(tiny_job):
    job, _, _ = tiny_job
    again = pipeline.run(pipeline.Job.load(job.root))
    assert all(r["skipped"] for r in again.values())


def test_failed_stage_resumes(tiny_job, monkeypatch):
    job, _, _ = tiny_job
    (job.stages_dir / "combined_sfm.json").unlink()  # as if it had failed before writing its marker
    assert pipeline.status(job)["combined_sfm"] == "pending"
    res = pipeline.run(job)
    assert [s for s, r in res.items() if not r["skipped"]] == ["combined_sfm"]


def test_a_changed_conf_reruns_that_stage_and_the_ones_after(tiny_job, monkeypatch):
    job, _, _ = tiny_job
    job2 = pipeline.Job.load(job.root)
    # a reducer conf that changes its output (fingerprints follow contents: an output the same byte for
    # byte leaves the stages after it up to date)
    job2.settings["transfer"] = {"pnp": {"enabled": False}}
    assert pipeline.is_done(job2, "match_views") and not pipeline.is_done(job2, "reduce")
    calls = []
    monkeypatch.setitem(
        pipeline.REGISTRY,
        "combined_sfm",
        dataclasses.replace(
            pipeline.REGISTRY["combined_sfm"], run=lambda j, r: calls.append("combined") or {}
        ),
    )
    res = pipeline.run(job2, stages=["match_views", "reduce", "combined_sfm"])
    assert res["match_views"]["skipped"] and not res["reduce"]["skipped"]
    assert calls == ["combined"]  # its input (the reducer's output) changed


def test_a_plan_without_views_fails_with_the_reason_and_keeps_the_plan(tiny_job):
    """No placement for any ground image: plan_views fails with a reason the CLI and the API show (a
    StageError), the plan in place and its marker stay."""
    job, _, _ = tiny_job
    plan = job.dir("plan") / "views.json"
    before, marker = plan.read_bytes(), (job.stages_dir / "plan_views.json").read_bytes()
    job2 = pipeline.Job.load(job.root)
    job2.settings["viewpoints"] = {"ground": {"placements": []}}
    with pytest.raises(pipeline.StageError, match=r"no intermediate view could be planned .*covered 0/4"):
        pipeline.run_stage(job2, "plan_views", force=True)
    assert plan.read_bytes() == before
    assert (job.stages_dir / "plan_views.json").read_bytes() == marker
    assert pipeline.is_done(pipeline.Job.load(job.root), "plan_views")


def test_splat_on_all_images(tiny_job):
    """The optional last stage: a 3DGS on every registered image of the combined model, aerial and
    ground, exported as PLY, with held-out metrics; not run unless selected."""
    import math

    from services.splat.ply import load_ply

    job, results, _ = tiny_job
    assert "splat_all" not in results and "splat_all" not in pipeline.status(job)
    res = pipeline.run(job, stages=["splat_all"])
    assert not res["splat_all"]["skipped"]
    rep = json.loads((job.dir("combined") / "report.json").read_text())
    m = json.loads((job.dir("splat_all") / "metrics.json").read_text())
    assert m["num_views"] == rep["num_registered"]  # every registered image, aerial and ground
    assert m["steps"] == 100 and math.isfinite(m["test"]["psnr"]) and m["test"]["psnr"] > 10.0
    splats = load_ply(job.dir("splat_all") / "point_cloud.ply")
    assert len(splats["means"]) == m["num_gaussians"] > 0
    assert pipeline.status(job)["splat_all"] == "done"


def test_gis_outputs_open_in_independent_readers(tiny_job):
    """combined/gis: the cameras as a GeoPackage (read here with sqlite3 and its WKB by hand), GeoJSON,
    omega/phi/kappa text and the points as LAS (its header and first record read by hand), all agreeing
    with the combined model."""
    import sqlite3
    import struct

    import numpy as np
    import pycolmap
    from pyproj import CRS, Transformer

    from services.evaluation.sfm import read_frame

    job, _, _ = tiny_job
    gis = job.dir("combined") / "gis"
    rep = json.loads((job.dir("combined") / "report.json").read_text())
    assert rep["gis"]["files"] == ["cameras.gpkg", "cameras.geojson", "cameras_opk.txt", "points.las"]
    crs = CRS.from_user_input(rep["gis"]["crs"])
    assert crs.is_projected and crs.to_epsg() == 32633  # Lund: UTM zone 33 (the POS is WGS84)
    rec = pycolmap.Reconstruction(str(job.dir("combined") / "sparse"))
    frame = read_frame(job.dir("combined") / "georef.json")
    to_utm = Transformer.from_crs("EPSG:4326", crs, always_xy=True)

    def utm(enu):
        lat, lon, h = frame.to_wgs84(np.asarray(enu, float)[None])
        x, y = to_utm.transform(lon[0], lat[0])
        return np.array([x, y, h[0]])

    registered = {im.name: im for im in rec.images.values() if im.has_pose}
    with sqlite3.connect(gis / "cameras.gpkg") as db:
        srs = db.execute("SELECT srs_id FROM gpkg_geometry_columns WHERE table_name='cameras'").fetchone()[0]
        assert srs == 32633
        rows = db.execute('SELECT name, "set", registered, reason, geom FROM cameras').fetchall()
    by_name = {r[0]: r for r in rows}
    unregistered = [g for g, d in rep["ground"].items() if not d["registered"]]
    assert set(by_name) == set(registered) | set(unregistered)
    for name, im in registered.items():
        blob = by_name[name][4]
        flags = blob[3]
        envelope = {0: 0, 1: 32, 2: 48, 3: 48, 4: 64}[(flags >> 1) & 7]
        order, gtype, x, y, z = struct.unpack("<BIddd", blob[8 + envelope : 8 + envelope + 29])
        assert gtype in (1001, 0x80000001)
        assert np.allclose([x, y, z], utm(im.projection_center()), atol=1e-3)
        assert by_name[name][2] == 1 and by_name[name][1] == name.split("/")[0]
    for g in unregistered:
        assert by_name[g][2] == 0 and by_name[g][3]  # the reason it did not register

    feats = json.loads((gis / "cameras.geojson").read_text())["features"]
    assert len(feats) == len(rows) and all(-180 < f["geometry"]["coordinates"][0] < 180 for f in feats)

    opk = [ln.split() for ln in (gis / "cameras_opk.txt").read_text().splitlines() if not ln.startswith("#")]
    assert {r[0] for r in opk} == set(registered)
    for name, *vals in opk:
        x, y, z, o, p, k = (float(v) for v in vals)
        o, p, k = np.radians([o, p, k])
        rx = np.array([[1, 0, 0], [0, np.cos(o), -np.sin(o)], [0, np.sin(o), np.cos(o)]])
        ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
        rz = np.array([[np.cos(k), -np.sin(k), 0], [np.sin(k), np.cos(k), 0], [0, 0, 1]])
        view = -(rx @ ry @ rz)[:, 2]  # the photogrammetric camera looks along -z
        axis = registered[name].cam_from_world().rotation.matrix().T[:, 2]  # COLMAP: along +z, ENU
        assert abs(np.degrees(np.arcsin(view[2])) - np.degrees(np.arcsin(axis[2]))) < 0.05  # same tilt
        assert np.allclose([x, y, z], utm(registered[name].projection_center()), atol=1e-3)

    data = (gis / "points.las").read_bytes()
    assert data[:4] == b"LASF" and data[24:26] == bytes([1, 4])  # LAS 1.4
    offset, fmt, length = struct.unpack_from("<IxxxxBH", data, 96)
    count = struct.unpack_from("<Q", data, 247)[0]
    scale, origin = struct.unpack_from("<3d", data, 131), struct.unpack_from("<3d", data, 155)
    assert fmt == 7 and count == rec.num_points3D()
    xi, yi, zi = struct.unpack_from("<3i", data, offset)
    first = sorted(rec.points3D.items())[0][1]
    got = np.array([xi, yi, zi]) * np.array(scale) + np.array(origin)
    assert np.allclose(got, utm(first.xyz), atol=2e-3)


def test_fingerprints_are_made_of_contents_not_times(tmp_path):
    """A stage's fingerprint follows its inputs' bytes: a file touched (or downloaded anew elsewhere)
    keeps it, a file rewritten with other bytes of the same size and time changes it."""
    import os

    root = tmp_path / "job"
    f = root / "sfm" / "sparse" / "points3D.bin"
    f.parent.mkdir(parents=True)
    f.write_bytes(b"a" * 64)
    fp = pipeline.fingerprint({"k": 1}, [root / "sfm"], root)
    st = f.stat()
    os.utime(f, ns=(st.st_atime_ns, st.st_mtime_ns + 10**12))
    assert pipeline.fingerprint({"k": 1}, [root / "sfm"], root) == fp
    f.write_bytes(b"b" * 64)
    os.utime(f, ns=(st.st_atime_ns, st.st_mtime_ns))  # same size, same time, other bytes
    assert pipeline.fingerprint({"k": 1}, [root / "sfm"], root) != fp
    assert pipeline.fingerprint({"k": 2}, [root / "sfm"], root) != pipeline.fingerprint(
        {"k": 1}, [root / "sfm"], root
    )
    # a copy of the job folder elsewhere (another worker) has the same fingerprint
    other = tmp_path / "elsewhere"
    (other / "sfm" / "sparse").mkdir(parents=True)
    (other / "sfm" / "sparse" / "points3D.bin").write_bytes(b"b" * 64)
    assert pipeline.fingerprint({"k": 1}, [other / "sfm"], other) == pipeline.fingerprint(
        {"k": 1}, [root / "sfm"], root
    )


def test_the_profile_sets_the_aerial_sfm_and_the_3dgs_size(tmp_path) -> None:
    """The cpu profile's SIFT SfM (1024 px, 4096 features, 12 neighbours) and 120k Gaussians, the gpu
    profile's paper scale; an option given wins, and ALIKED features keep their own conf."""
    from services.pipeline import Job, JobOptions

    def confs(**options) -> tuple[dict, dict]:
        job = Job(tmp_path, {}, JobOptions.model_validate(options), {"splat_backend": "cpu"})
        return job.sfm_conf(), job.splat_conf()

    sfm, splat = confs()
    assert (sfm["features"]["max_image_size"], sfm["features"]["max_num_features"]) == (1024, 4096)
    assert sfm["matching"]["num_neighbors"] == 12 and splat["strategy"]["max_gaussians"] == 120_000
    sfm, splat = confs(profile="gpu")
    assert (sfm["features"]["max_image_size"], sfm["features"]["max_num_features"]) == (1600, 8192)
    assert sfm["matching"]["num_neighbors"] == 20 and splat["strategy"]["max_gaussians"] == 0
    sfm, splat = confs(sfm_max_image_size=2000, splat_max_gaussians=0)
    assert sfm["features"]["max_image_size"] == 2000 and splat["strategy"]["max_gaussians"] == 0
    sfm, _ = confs(sfm_features="aliked")
    assert sfm["features"]["type"] == "aliked" and sfm["features"]["max_image_size"] == 1600  # SIFT's only


def test_every_stage_runs_on_the_jobs_torch_threads(tiny_job, monkeypatch):
    """settings["torch_threads"] holds in every stage (the planning ran on torch's default two threads
    beside the demo's baselines, 5x slower), not only in those that set it themselves."""
    import torch

    job, _, _ = tiny_job
    seen = []
    monkeypatch.setitem(
        pipeline.REGISTRY,
        "plan_views",
        dataclasses.replace(
            pipeline.REGISTRY["plan_views"], run=lambda j, r: seen.append(torch.get_num_threads()) or {}
        ),
    )
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        pipeline.run_stage(pipeline.Job.load(job.root), "plan_views", force=True)
    finally:
        torch.set_num_threads(before)
    assert seen == [1]
