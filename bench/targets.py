"""How far the ground-aware planner's targets are from the truth, per planner setting.

    python bench/targets.py --job runs/bench/m-small-walk/splat-both \
        --scene runs/bench/scene-small-walk-seed0 [--variant NAME:KEY=VALUE[,KEY=VALUE]] [--json FILE]

The ground-aware planner aims each ground camera's views at its target: where the camera's principal
ray (at its POS pose, the way the planner sees it) meets the scene beyond `ground.min_target_m`. This
loads the planner's scene of a method job (bench/method.py) with the job's depth probe (its renderer
without colour), finds every ground camera's target with the job's viewpoint conf and with each
--variant's overrides (services.views confs keys), and compares the target's distance along the ray
with the truth's (the synthetic scene ray cast at the same pose, from min_target_m on): per variant the
number of targets within 15% of the true distance (of the ground cameras whose ray meets something
within max_target_m), the median relative miss, and how each target was found (depth probe, sparse
points, terrain, look-ahead).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from services import pipeline  # noqa: E402
from services.colmap_model import Pose  # noqa: E402
from services.conf import merge_conf, parse_overrides  # noqa: E402
from services.geometry import optical_axis  # noqa: E402
from services.views import GroundTruthRenderer, rendering  # noqa: E402
from services.views.confs import BASE  # noqa: E402
from services.views.ground_aware import ground_target  # noqa: E402
from services.views.scene import Scene, depth_at_center, load_scene, probe_camera  # noqa: E402


def true_distances(scene: Scene, truth: GroundTruthRenderer, conf: dict) -> dict[str, float | None]:
    """Per ground camera, the true distance along its principal ray to the first surface beyond
    min_target_m (None where it meets nothing within max_target_m)."""
    gc, tc = conf["ground"], conf["target"]
    out: dict[str, float | None] = {}
    for g, pose in sorted(scene.ground_poses.items()):
        c, d = pose.center, optical_axis(pose)
        start = float(gc["min_target_m"])
        probe = probe_camera(scene.ground_cameras[g], tc["probe_width"])
        depth = truth.render(probe, Pose.from_center(pose.R.T, c + start * d))[1]
        z = depth_at_center(depth, tc["depth_window"])
        out[g] = start + float(z) if z is not None and start + z <= gc["max_target_m"] else None
    return out


def target_figures(scene: Scene, conf: dict, truth: dict[str, float | None]) -> dict:
    """The targets of `conf` against the true distances: counts, median miss, per image."""
    rows, misses, how_counts = {}, [], {}
    for g in sorted(scene.ground_poses):
        T, how = ground_target(g, scene, conf)
        pose = scene.ground_poses[g]
        t = float((T - pose.center) @ optical_axis(pose))
        rows[g] = {"distance_m": round(t, 2), "from": how, "true_m": truth[g] and round(truth[g], 2)}
        how_counts[how] = how_counts.get(how, 0) + 1
        if truth[g]:
            misses.append(abs(t - truth[g]) / truth[g])
    misses_a = np.array(misses)
    return {
        "within_15pct": int((misses_a <= 0.15).sum()),
        "with_truth": len(misses),
        "median_relative_miss": float(np.median(misses_a)) if len(misses_a) else None,
        "found_by": how_counts,
        "per_image": rows,
    }


def parse_variant(text: str) -> tuple[str, list[str]]:
    name, _, sets = text.partition(":")
    return name, [s for s in sets.split(",") if s]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--job", type=Path, required=True, help="a method job folder (bench/method.py)")
    ap.add_argument("--scene", type=Path, required=True, help="its synthetic scene folder")
    ap.add_argument(
        "--variant",
        action="append",
        default=[],
        help="NAME:KEY=VALUE[,KEY=VALUE] viewpoint conf overrides, repeatable: "
        "probe:target.probe_from_min=true",
    )
    ap.add_argument("--json", type=Path, help="write the figures here")
    args = ap.parse_args()
    job = pipeline.Job.load(args.job)
    base = merge_conf(BASE, job.viewpoint_conf())
    variants = {"job": base}
    for text in args.variant:
        name, sets = parse_variant(text)
        variants[name] = merge_conf(base, parse_overrides(sets, base))
    depth_fn = rendering.depth_fn(job.renderer(blocks=False, colour=False))
    truth = GroundTruthRenderer(args.scene, job.sfm.sparse)
    figures, distances = {}, None
    for name, conf in variants.items():
        scene = load_scene(job.sfm.sparse, job.pos, job.cameras, job.sfm.georef, depth_fn, conf)
        if distances is None:
            distances = true_distances(scene, truth, conf)
        figures[name] = target_figures(scene, conf, distances)
        f = figures[name]
        miss = f["median_relative_miss"]
        print(
            f"{name}: {f['within_15pct']}/{f['with_truth']} targets within 15% of the true distance, "
            f"median miss {100 * miss:.0f}%, found by {f['found_by']}"
            if miss is not None
            else f"{name}: no ground camera's ray meets the truth within max_target_m"
        )
    if args.json:
        git = ["git", "rev-parse", "--short", "HEAD"]
        commit = subprocess.run(git, capture_output=True, text=True, cwd=ROOT).stdout.strip()
        doc = {"command": " ".join(["python", *sys.argv]), "commit": commit, "figures": figures}
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(doc, indent=1))
        print("figures:", args.json)


if __name__ == "__main__":
    main()
