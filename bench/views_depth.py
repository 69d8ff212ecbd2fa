"""The views' depth against the truth at a job's planned views, on the pixels the aerial images see.

    python bench/views_depth.py --job runs/bench/method-isprs-seed0/splat-ground-aware \
        --scene runs/bench/scene-isprs-seed0 --depths splat,proxy,sweep --width 512 \
        [--sweep-set KEY=VALUE] [--limit 20] [--at views|ground] [--json docs/results/views-depth.json]

A view coloured from the aerial images shows each one's texture where the view's depth puts it: the depth
decides whether that texture lands where the ground image has it. For every planned view of the job
(plan/views.json, `--limit` of them evenly spread) this renders the depth of each candidate at `--width`
with the job's renderer (services.views.rendering, conf depth per candidate; "splat" is the 3DGS's own
depth) and the true depth (the synthetic scene ray cast in the aerial model's frame), and keeps the
pixels whose true surface two aerial images see (nothing else can be coloured from them). With
`--at ground` the cameras are the ground images' own, at their true poses (what a view planned at a
ground camera shows, and the depth that lifts a ground image's pixels onto the aerial surface). Per
candidate: the median relative depth error there (a pixel without depth counts as wrong), the share
within 2% and 5%, and seconds per view. Figures pool the pixels of all views.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from method import aerial_seen_count, aerial_truth_depths  # noqa: E402

from services import pipeline  # noqa: E402
from services.colmap_model import Camera, Pose  # noqa: E402
from services.conf import merge_conf  # noqa: E402
from services.geometry import scaled_camera  # noqa: E402


def candidate_renderer(job: pipeline.Job, base: dict, depth: str, sweep_over: dict, over: dict | None = None):
    """The job's views' renderer with its views' conf `base` and the depth `depth` ("splat": the 3DGS
    alone), `over` set in that depth's conf (the proxy's for "proxy" and "stereo", the sweep's, on top
    of `sweep_over`, for "sweep"; a key "tracks.KEY" sets the learned tracks' conf, services.views.tracks)."""
    if depth == "splat":
        from services.views import SplatRenderer

        return SplatRenderer(job.splat.dir, job.settings["splat_backend"], job.render_conf()["min_alpha"])
    over = dict(over or {})
    tracks = {k.split(".", 1)[1]: over.pop(k) for k in list(over) if k.startswith("tracks.")}
    views = {"depth": depth, "sweep": sweep_over, "proxy": {}, "tracks": tracks}
    if depth in ("proxy", "stereo"):
        views["proxy"] = over
    else:
        views["sweep"] = {**sweep_over, **over}
    job.settings["views"] = merge_conf(base, views)
    return job.renderer(blocks=False)


def seen_pixels(gt, aerial: list, camera: Camera, pose: Pose) -> tuple[np.ndarray, np.ndarray]:
    """(the true z-depth (H, W), the pixels whose true surface at least two aerial images see)."""
    d = gt.render(camera, pose)[1]
    v, u = np.nonzero(d > 0)
    X = pose.unproject(camera.K, np.stack([u + 0.5, v + 0.5], 1), d[v, u].astype(float))
    mask = np.zeros(d.shape, bool)
    mask[v, u] = aerial_seen_count(X, aerial) >= 2
    return d, mask


def planned_views(job: pipeline.Job) -> list[tuple[Camera, Pose]]:
    """The job's planned views (plan/views.json): (camera, pose) each."""
    views = json.loads(job.plan.views.read_text())["views"]
    return [
        (Camera(**v["camera"]), Pose(np.asarray(v["pose"]["R"], float), np.asarray(v["pose"]["t"], float)))
        for v in views
    ]


def ground_cameras(scene: Path, gt) -> list[tuple[Camera, Pose]]:
    """The scene's ground cameras at their true poses, taken into the aerial model's frame (the inverse of
    the truth renderer's truth_from_model similarity)."""
    from services.colmap_model import read_model

    cameras, poses = read_model(scene / "gt" / "sparse")
    out = []
    for name in sorted(n for n in poses if n.startswith("ground/")):
        p = poses[name]
        center = gt.R.T @ (p.center - gt.t) / gt.s
        # the model's cam_from_world: cam_from_truth after truth_from_model's rotation
        R = p.R @ gt.R
        out.append((cameras[name], Pose.from_center(R.T, center)))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--job", type=Path, required=True, help="a job folder with planned views (plan/views.json)"
    )
    ap.add_argument("--scene", type=Path, required=True, help="the job's synthetic scene folder")
    ap.add_argument(
        "--depths",
        default="splat,proxy,sweep",
        help="comma-separated: splat, proxy, sweep, stereo; a variant as KIND@KEY=VALUE@KEY=VALUE (keys of "
        "the proxy's conf for proxy and stereo, of the sweep's for sweep; tracks.KEY: the learned tracks')",
    )
    ap.add_argument("--width", type=int, default=512, help="views are measured this wide")
    ap.add_argument("--limit", type=int, default=0, help="at most this many views, evenly spread (0: all)")
    ap.add_argument(
        "--at",
        choices=("views", "ground"),
        default="views",
        help="the job's planned views, or the ground cameras at their true poses",
    )
    ap.add_argument("--sweep-set", action="append", default=[], metavar="KEY=VALUE", help="sweep conf entry")
    ap.add_argument("--json", type=Path, help="write the figures here")
    args = ap.parse_args(argv)
    from services.views import GroundTruthRenderer

    job = pipeline.Job.load(args.job)
    base_views = dict(job.settings.get("views", {}))
    sweep_over = {k: json.loads(v) for k, v in (kv.split("=", 1) for kv in args.sweep_set)}
    gt = GroundTruthRenderer(args.scene, job.sfm.sparse)
    cams = ground_cameras(args.scene, gt) if args.at == "ground" else planned_views(job)
    if args.limit and len(cams) > args.limit:
        cams = [cams[i] for i in np.linspace(0, len(cams) - 1, args.limit).round().astype(int)]
    aerial = aerial_truth_depths(gt, job.sfm.sparse, 480)
    truths = []
    for cam, pose in cams:
        cam = scaled_camera(cam, args.width)
        truths.append((cam, pose, *seen_pixels(gt, aerial, cam, pose)))
    figures: dict = {
        "at": args.at,
        "views": len(cams),
        "width_px": args.width,
        "seen_pixels": int(sum(t[3].sum() for t in truths)),
    }
    for depth in [d.strip() for d in args.depths.split(",") if d.strip()]:
        kind, *over = depth.split("@")  # "sweep@range=0.1@min_gain=0.2": a sweep variant
        extra = {k: json.loads(v) for k, v in (kv.split("=", 1) for kv in over)}
        renderer = candidate_renderer(job, base_views, kind, sweep_over, extra)
        rel, t0 = [], time.perf_counter()
        for cam, pose, truth, seen in truths:
            d = renderer.render(cam, pose)[1]
            r = np.where(d[seen] > 0, np.abs(d[seen] - truth[seen]) / truth[seen], np.inf)
            rel.append(r)
        r = np.concatenate(rel)
        figures[depth] = {
            "median_rel_error": float(np.median(r)),
            "within_2pct": float((r <= 0.02).mean()),
            "within_5pct": float((r <= 0.05).mean()),
            "no_depth": float(np.isinf(r).mean()),
            "off_over_25pct": float(((r > 0.25) & np.isfinite(r)).mean()),
            "per_view_median": [round(float(np.median(x)), 4) if len(x) else None for x in rel],
            "seconds_per_view": round((time.perf_counter() - t0) / max(len(truths), 1), 2),
        }
        print(
            f"{depth:8s} median rel error {figures[depth]['median_rel_error']:.4f}  within 2% "
            f"{figures[depth]['within_2pct']:.3f}  within 5% {figures[depth]['within_5pct']:.3f}  none "
            f"{figures[depth]['no_depth']:.3f}  over 25% {figures[depth]['off_over_25pct']:.3f}  "
            f"{figures[depth]['seconds_per_view']:.1f} s/view",
            flush=True,
        )
    from services.views.rendering import confs as render_confs

    default = render_confs["default"]["depth"]  # the product's views' depth: its figures at the top
    if default in figures:
        figures.update(
            default=default,
            median_rel_error=figures[default]["median_rel_error"],
            within_2pct=figures[default]["within_2pct"],
        )
    if args.json:
        commit = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True
        ).stdout.strip()
        doc = {"command": "python bench/views_depth.py " + " ".join(argv or sys.argv[1:]), "commit": commit}
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({**doc, "figures": figures}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
