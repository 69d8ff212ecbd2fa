"""How well 3DGS models render the intermediate views, against the true scene at the same cameras.

    python bench/splat_views.py --scene runs/bench/scene-small-walk-seed0 \
        --sparse runs/bench/method-small-walk-seed0/base/sfm/sparse \
        --views runs/bench/method-small-walk-seed0/splat-both/plan/views.json \
        --splat base=runs/bench/method-small-walk-seed0/base/splat --splat reg=runs/splat-reg

The held-out PSNR of 3DGS training measures aerial views; the views midview matches are lower and
tilted, where a model trained from the air smears and grows floaters. For every planned view (a
views.json of services.views.planning) this renders the true scene (services.views.GroundTruthRenderer,
aligned to the aerial model) and each 3DGS model at a reduced width, and prints per model: PSNR and
SSIM on the pixels where the truth has a surface (no sky), the median relative depth error, the
fraction of pixels whose depth is within 5% of the truth, and matchability: ALIKED+LightGlue matches
between the render and the true render (same camera) that land within 3 px of each other, what the
matching stage needs of a view (PSNR and SSIM are dominated by low frequencies: a sharper model that
finds many more correct matches scores about the same). Ratios are against the first model. With
--source-images each model is also measured with its views coloured from the aerial images through the
plane proxy (render_views' default colour).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from services.colmap_model import Camera, Pose  # noqa: E402
from services.geometry import scaled_camera  # noqa: E402
from services.splat.loss import ssim  # noqa: E402
from services.views import GroundTruthRenderer, SplatRenderer  # noqa: E402


def view_metrics(rgb: np.ndarray, depth: np.ndarray, rgb_gt: np.ndarray, depth_gt: np.ndarray) -> dict:
    """PSNR / SSIM on the truth's surface pixels and depth agreement of one render (uint8 (H, W, 3),
    z-depth (H, W), 0 = none) against the truth."""
    mask = depth_gt > 0
    a = rgb.astype(np.float32) / 255.0
    b = rgb_gt.astype(np.float32) / 255.0
    mse = float(((a - b) ** 2)[mask].mean()) if mask.any() else float("nan")
    b_masked = np.where(mask[..., None], b, a)  # sky pixels do not count against SSIM
    s = float(ssim(torch.from_numpy(a), torch.from_numpy(b_masked)))
    both = mask & (depth > 0)
    rel = np.abs(depth[both] - depth_gt[both]) / depth_gt[both] if both.any() else np.array([np.nan])
    return {
        "psnr": -10.0 * np.log10(max(mse, 1e-10)),
        "ssim": s,
        "depth_rel_median": float(np.median(rel)),
        "depth_within_5pct": float((rel <= 0.05).sum() / max(mask.sum(), 1)),
    }


def features(conf: dict, rgb: np.ndarray) -> dict:
    """ALIKED features of a render, with its size as the matcher wants it."""
    from services.matching.features import extract

    feats = extract(conf["features"], rgb)
    feats["image_size"] = np.array([rgb.shape[1], rgb.shape[0]], np.int64)
    return feats


def matchable(conf: dict, feats_gt: dict, rgb: np.ndarray, px: float = 3.0) -> int:
    """Matches of a render with the true render of the same camera that agree within `px` pixels."""
    from services.matching.direct import match_features

    feats = features(conf, rgb)
    m, _ = match_features(feats, feats_gt, conf["matcher"])
    if len(m) == 0:
        return 0
    d = np.linalg.norm(feats["keypoints"][m[:, 0]] - feats_gt["keypoints"][m[:, 1]], axis=1)
    return int((d <= px).sum())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", type=Path, required=True, help="a synthetic scene folder (midview synth)")
    ap.add_argument("--sparse", type=Path, required=True, help="the aerial SfM model the 3DGS models used")
    ap.add_argument("--views", type=Path, required=True, help="a views.json of planned views")
    ap.add_argument(
        "--splat",
        action="append",
        required=True,
        help="LABEL=PATH of a 3DGS training folder, or of trained blocks (a folder with plan.json)",
    )
    ap.add_argument("--width", type=int, default=512, help="render width (the views' field of view)")
    ap.add_argument("--limit", type=int, default=0, help="at most this many views, evenly spread (0: all)")
    ap.add_argument("--backend", default="auto")
    ap.add_argument("--keypoints", type=int, default=1024, help="ALIKED keypoints for matchability (0: skip)")
    ap.add_argument(
        "--source-images",
        type=Path,
        help="the aerial images' folder: also measure each model's views coloured from them through the "
        "plane proxy (services.views.SourceRenderer, label LABEL+source), render_views' default",
    )
    ap.add_argument(
        "--depths",
        default="proxy",
        help="with --source-images, comma-separated views' depths to measure: proxy (LABEL+source, "
        "render_views' default), stereo (LABEL+stereo: the aerial images' dense stereo, "
        "services.views.stereo), truth (LABEL+truth: the true depth, the bound of colour from the aerial "
        "images)",
    )
    ap.add_argument(
        "--stereo-set", action="append", default=[], metavar="KEY=VALUE", help="stereo conf entry, repeatable"
    )
    ap.add_argument("--out", type=Path, help="write the per-view figures here (JSON)")
    args = ap.parse_args()

    models = {}
    for item in args.splat:
        label, _, path = item.partition("=")
        if (Path(path) / "plan.json").exists():  # trained blocks (bench/splat_blocks.py, a job's blocks/)
            from services.views import BlockRenderer

            model = json.loads((Path(path) / "plan.json").read_text())["model"]
            models[label] = BlockRenderer(model, path, args.backend, 0.5)
        else:
            models[label] = SplatRenderer(path, args.backend, 0.5)
    if args.source_images:
        from services.conf import merge_conf, parse_overrides
        from services.views import SourceRenderer
        from services.views.stereo import confs as stereo_confs

        base = stereo_confs["default"]
        stereo = merge_conf(base, parse_overrides(args.stereo_set, base))
        for label in list(models):
            for kind in args.depths.split(","):
                name = f"{label}+source" if kind == "proxy" else f"{label}+{kind}"
                conf = {"depth": kind, "stereo": stereo}
                models[name] = SourceRenderer(
                    models[label], args.sparse, args.source_images, conf, scene=args.scene
                )
    views = json.loads(args.views.read_text())["views"]
    if args.limit and len(views) > args.limit:
        views = [views[i] for i in np.linspace(0, len(views) - 1, args.limit).round().astype(int)]
    gt = GroundTruthRenderer(args.scene, args.sparse)
    mconf = None
    if args.keypoints:
        from services.matching.views import confs as match_confs
        from services.matching.views import feature_conf

        mconf = {**match_confs["aliked-lightglue"], "max_keypoints": args.keypoints}
        mconf = {"features": feature_conf(mconf), "matcher": mconf["matcher"]}
    per_view: dict[str, dict[str, dict]] = {k: {} for k in models}
    seconds = {k: 0.0 for k in ["truth", *models]}
    for v in views:
        cam = scaled_camera(Camera(**v["camera"]), args.width)
        pose = Pose(np.asarray(v["pose"]["R"], float), np.asarray(v["pose"]["t"], float))
        t0 = time.perf_counter()
        rgb_gt, depth_gt = gt.render(cam, pose)
        seconds["truth"] += time.perf_counter() - t0
        feats_gt = None
        if mconf is not None:
            feats_gt = features(mconf, rgb_gt)
        for label, m in models.items():
            t0 = time.perf_counter()
            rgb, depth = m.render(cam, pose)
            seconds[label] += time.perf_counter() - t0
            per_view[label][v["name"]] = view_metrics(rgb, depth, rgb_gt, depth_gt)
            if feats_gt is not None:
                per_view[label][v["name"]]["matchable"] = matchable(mconf, feats_gt, rgb)
    first = next(iter(models))
    keys = ("psnr", "ssim", "depth_rel_median", "depth_within_5pct") + (("matchable",) if mconf else ())
    means = {k: {m: float(np.nanmean([r[m] for r in per_view[k].values()])) for m in keys} for k in models}
    print(f"{len(views)} views at {args.width} px wide (means over the views; ratios against {first!r})")
    cols = ("PSNR dB", 9), ("SSIM", 8), ("depth err", 11), ("depth<5%", 10), ("matchable", 11), ("x", 7)
    print(f"{'model':<16}" + "".join(f"{c:>{w}}" for c, w in cols) + f"{'s/view':>8}")
    for k in models:
        r = means[k]
        m = r.get("matchable", float("nan"))
        ratio = m / means[first]["matchable"] if mconf and means[first]["matchable"] else float("nan")
        print(
            f"{k:<16}{r['psnr']:>9.2f}{r['ssim']:>8.3f}{r['depth_rel_median']:>11.3f}"
            f"{r['depth_within_5pct']:>10.3f}{m:>11.1f}{ratio:>7.2f}{seconds[k] / len(views):>8.2f}"
        )
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps({"means": means, "views": per_view}, indent=1))


if __name__ == "__main__":
    main()
