"""bench/targets.py's figures: targets against the true distance along the ground cameras' rays."""

import numpy as np
import pytest
from test_bench_splat_views import load_bench
from test_viewpoints import make_scene, pose_ypr, raycast

from services import views as vp
from services.conf import merge_conf


@pytest.fixture(scope="module")
def bench():
    return load_bench("targets")


class Truth:
    """The analytic scene of tests/test_viewpoints.py (terrain, a wall at y = 0) as a truth renderer."""

    def render(self, camera, pose):
        return np.zeros((camera.height, camera.width, 3), np.uint8), raycast(camera, pose)


def test_targets_are_counted_against_the_true_distance(bench):
    """Two cameras facing the wall 25 m and 15 m ahead, one facing away from it (its ray meets nothing
    within max_target_m: not counted). With the true depth as the probe every counted target is within
    15%; behind a floater 1.5 m ahead the first falls back to look-ahead (15 m for 25 m: a 40% miss)
    unless the probe stands min_target_m ahead."""
    ground = {
        "ground/G0001.jpg": pose_ypr([0.0, -25.0, 1.6], 0.0, 0.0),
        "ground/G0002.jpg": pose_ypr([10.0, -15.0, 1.6], 0.0, 0.0),
        "ground/G0003.jpg": pose_ypr([20.0, -15.0, 1.6], 180.0, 0.0),
    }
    scene = make_scene(ground)
    conf = vp.confs["ground-aware"]
    truth = bench.true_distances(scene, Truth(), conf)
    assert truth["ground/G0001.jpg"] == pytest.approx(25.0, abs=0.1)
    assert truth["ground/G0002.jpg"] == pytest.approx(15.0, abs=0.1)
    assert truth["ground/G0003.jpg"] is None
    scene.depth_fn = raycast
    exact = bench.target_figures(scene, conf, truth)
    assert exact["within_15pct"] == exact["with_truth"] == 2 and exact["median_relative_miss"] < 0.01
    assert exact["found_by"]["depth"] == 2
    scene.depth_fn = lambda camera, pose: raycast(camera, pose, hole=(-23.5, 50.0, 50.0))
    floater = bench.target_figures(scene, conf, truth)
    assert floater["within_15pct"] == 1 and floater["per_image"]["ground/G0001.jpg"]["from"] == "look-ahead"
    _, sets = bench.parse_variant("probe:target.probe_from_min=true")
    past = bench.target_figures(scene, merge_conf(conf, {"target": {"probe_from_min": True}}), truth)
    assert sets == ["target.probe_from_min=true"] and past["within_15pct"] == 2
