"""`midview demo`'s direct baselines in a child process beside the pipeline: the same match files as
in-process, a log of their own, and a child that stops when the demo does."""

from __future__ import annotations

import os
import time

import numpy as np
import pytest

from cli.demo import BaselinesBeside, direct_baselines
from services.matching import features as features_mod
from services.matching.views import feature_conf
from shared.images import list_images
from shared.matchfile import MatchFile

ALIKED = feature_conf({"features": "aliked", "max_keypoints": 256, "resize_max": 320})
SIFT = {"features": {**feature_conf({"features": "sift", "max_keypoints": 512, "resize_max": 320})}}


def _pairs(path):
    with MatchFile(path) as mf:
        return {(pm.name0, pm.name1): pm.matches[pm.inliers] for pm in mf.iter_pairs()}


@pytest.mark.slow
def test_baselines_beside_match_what_in_process_does(tiny_scene, tmp_path):
    child = BaselinesBeside(tiny_scene, tmp_path / "beside", ALIKED, SIFT)
    try:
        found, seconds = child.wait(timeout=600)
    finally:
        child.stop()
    assert set(found) == {"direct SIFT", "direct ALIKED+LightGlue"} and seconds > 0
    log = child.log.read_text()
    assert "direct-alg.h5" in log and "match direct-sift" in log  # its log and its progress bars
    # midview's features, handed to the job: every image of the survey, not extracted again
    dst = tmp_path / "job" / "features" / child.features.name
    assert child.share_features(dst) and not child.share_features(dst)
    names = list_images(tiny_scene / "images")
    features_mod.main(ALIKED, tiny_scene / "images", names, dst)
    assert dst.stat().st_mtime_ns == child.features.stat().st_mtime_ns  # all cached: left untouched
    here = direct_baselines(tiny_scene, tmp_path / "here", ALIKED, SIFT)
    total = 0
    for label, (path, _) in found.items():
        a, b = _pairs(path), _pairs(here[label][0])
        assert a.keys() == b.keys() and a
        assert all(np.array_equal(a[k], b[k]) for k in a)
        total += sum(len(m) for m in a.values())
    assert total > 0


def test_a_failed_demo_stops_the_baselines(tiny_scene, tmp_path):
    child = BaselinesBeside(tiny_scene, tmp_path, ALIKED, SIFT)
    time.sleep(3.0)
    t0 = time.perf_counter()
    child.stop()
    assert time.perf_counter() - t0 < 30 and not child.proc.is_alive()
    assert not (tmp_path / "baselines.json").exists()


def test_a_failing_child_says_where_its_log_is(tmp_path):
    child = BaselinesBeside(tmp_path / "no-scene", tmp_path / "out", ALIKED, SIFT)
    with pytest.raises(RuntimeError, match="baselines.log"):
        child.wait(timeout=120)
    assert "Traceback" in child.log.read_text()


@pytest.mark.slow
def test_the_child_reconstructs_the_baselines_once_the_aerial_model_is_ready(tiny_scene, tmp_path):
    """Given the job, the child waits for the parent's word that the aerial model is done, then makes
    the baselines' combined reconstructions beside the pipeline: the same as the demo makes in-process."""
    from cli.demo import _LogConsole, reconstruct_baselines
    from services import pipeline

    images = tiny_scene / "images"
    job = pipeline.Job.create(
        tmp_path / "demo" / "job", images / "aerial", images / "ground", tiny_scene / "pos.csv",
        tiny_scene / "cameras.json", settings={"sfm": {"features": {"max_num_features": 2048}}},
    )  # fmt: skip
    child = BaselinesBeside(tiny_scene, tmp_path / "demo" / "baselines", ALIKED, SIFT, job.root)
    try:
        pipeline.run(job, stages=["aerial_sfm"])
        deadline = time.monotonic() + 300
        while not (child.out_dir / "direct-alg.h5").exists() and time.monotonic() < deadline:
            time.sleep(0.5)
        time.sleep(3.0)  # its matching is done: it waits for the word, writing no result
        assert child.proc.is_alive() and not (child.out_dir / "baselines.json").exists()
        child.pipeline_done()  # the reconstructions to come take every core
        child.aerial_model_ready()
        found, _ = child.wait(timeout=600)
    finally:
        child.stop()
    assert child.sfm is not None and set(child.sfm) == set(found) and child.sfm_seconds > 0
    if (os.cpu_count() or 1) > 1:
        assert "the baselines take every core" in child.log.read_text()
    here = reconstruct_baselines(job, found, tiny_scene, tmp_path / "here", _LogConsole())
    assert set(here) == set(child.sfm)
    for label, ev in here.items():
        mine = child.sfm[label]["per_set"]["ground"]
        assert mine["num_registered"] == ev["per_set"]["ground"]["num_registered"]
        assert isinstance(mine["num_registered"], int) and isinstance(child.sfm[label]["num_points3D"], int)
