"""bench/splat_views.py's figures of one render against the truth: exact, blurred, shifted."""

import importlib.util
from pathlib import Path

import cv2
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


def load_bench(name: str):
    """The module of bench/NAME.py (bench/ is no package)."""
    spec = importlib.util.spec_from_file_location(name, ROOT / "bench" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def bench():
    return load_bench("splat_views")


@pytest.fixture(scope="module")
def truth():
    """A textured image (random rectangles and discs) with a band of sky."""
    g = np.random.default_rng(0)
    rgb = np.full((384, 512, 3), 128, np.uint8)
    for _ in range(250):
        c = tuple(int(v) for v in g.integers(0, 256, 3))
        x, y = (int(v) for v in g.integers(0, 512, 2))
        if g.random() < 0.5:
            cv2.rectangle(
                rgb, (x, y % 384), (x + int(g.integers(5, 40)), y % 384 + int(g.integers(5, 40))), c, -1
            )
        else:
            cv2.circle(rgb, (x, y % 384), int(g.integers(3, 20)), c, -1)
    depth = np.full(rgb.shape[:2], 10.0, np.float32)
    depth[:40] = 0.0  # sky: no surface
    return rgb, depth


def test_view_metrics(bench, truth):
    rgb, depth = truth
    same = bench.view_metrics(rgb, depth, rgb, depth)
    assert same["psnr"] > 90 and same["ssim"] == pytest.approx(1.0, abs=1e-4)
    assert same["depth_rel_median"] == 0.0
    assert same["depth_within_5pct"] == 1.0  # of the pixels with a true surface
    blurred = bench.view_metrics(cv2.GaussianBlur(rgb, (0, 0), 3), depth * 1.1, rgb, depth)
    assert blurred["psnr"] < 35 and blurred["ssim"] < 0.9
    assert blurred["depth_rel_median"] == pytest.approx(0.1, rel=1e-3) and blurred["depth_within_5pct"] == 0.0


def test_matchability_falls_with_blur_and_misplacement(bench, truth):
    rgb, _ = truth
    from services.matching.features import confs

    conf = {"features": confs["aliked"], "matcher": {"name": "lightglue", "features": "aliked"}}
    feats = bench.features(conf, rgb)
    exact = bench.matchable(conf, feats, rgb)
    blurred = bench.matchable(conf, feats, cv2.GaussianBlur(rgb, (0, 0), 4))
    shifted = bench.matchable(conf, feats, np.roll(rgb, 8, axis=1))  # right content, 8 px off
    assert exact > 0.8 * len(feats["keypoints"])
    assert blurred < 0.5 * exact
    assert shifted < 0.1 * exact
