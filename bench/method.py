"""midview against the direct baselines on a rendered synthetic survey (default: the `isprs` preset).

    python bench/method.py [--preset isprs] [--seed 0] [--renderers gt,splat]
                           [--planners paper,ground-aware,both] [--views 2] [--max-keypoints 1024]
                           [--matchers aliked-lightglue,sift] [--sift-keypoints 8192]
                           [--splat-steps 1500] [--splat-set KEY=VALUE] [--view-set KEY=VALUE]
                           [--match-set KEY=VALUE] [--adopt-sfm DIR] [--adopt-splat DIR] [--out DIR]

One aerial SfM (and one 3DGS model) is shared by every configuration: a base job runs aerial_sfm and
train_splat, and one job per (renderer, planner) links to it and runs plan_views .. combined_sfm (the
"both" planner reuses the matches of the two others: they are the same views). The renderers: "splat"
(the product: the 3DGS model) and "gt" (the ground-truth ray caster: the upper bound a perfect 3DGS
would reach). Baselines: direct ALIKED+LightGlue on the POS pairs with the same features (keypoint budget)
as midview, and, when bench/baselines.py has been run on the scene, its SIFT and ALIKED+LightGlue (2048
keypoints) match files. Everything is evaluated on the co-visible pairs of the ground truth (GT-correct:
within 3 px through the true depth), the combined reconstructions with `evaluate_sfm`, and the PnP
ground-camera poses of the reducer against the true camera centres. The keypoint bound of each match file
(services.evaluation.keypoint_bound) says how many GT-correct matches its keypoints allow at most: a
method cannot exceed it whatever it matches. Matchers of the views: "aliked-lightglue" (--max-keypoints)
and "sift" (--sift-keypoints, at 1600 px), each a configuration of its own (job folder suffix -sift).
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from services import pipeline  # noqa: E402
from services.synth import scene_complete  # noqa: E402
from shared.logging import setup_logging  # noqa: E402

logger = logging.getLogger("midview.bench.method")

DEFAULT_TEXTURES = ROOT.parent / "shared" / "data" / "lund_street"
SHARED = ("sfm", "splat", "features")  # stage folders of the base job, linked into every configuration


def ensure_scene(preset: str, seed: int, scene: Path, textures: Path | None) -> Path:
    if scene_complete(scene):
        return scene
    from services import synth

    logger.info("rendering preset %s (seed %d) into %s", preset, seed, scene)
    synth.main(synth.confs[preset], scene, seed=seed, textures_dir=textures, overwrite=True)
    return scene


def make_job(root: Path, scene: Path, options: dict, settings: dict) -> pipeline.Job:
    return pipeline.Job.create(
        root,
        scene / "images" / "aerial",
        scene / "images" / "ground",
        scene / "pos.csv",
        scene / "cameras.json",
        options=options,
        settings=settings,
    )


def link_base(job: pipeline.Job, base: pipeline.Job) -> None:
    """Share the base job's aerial SfM, 3DGS model and feature cache (links), and its stage markers."""
    for d in SHARED:
        src, dst = base.dir(d), job.dir(d)
        src.mkdir(parents=True, exist_ok=True)
        if dst.is_symlink():
            continue
        if dst.exists():
            shutil.rmtree(dst)
        dst.symlink_to(src.resolve(), target_is_directory=True)
    if base.cameras.exists():
        shutil.copy2(base.cameras, job.cameras)
    job.stages_dir.mkdir(parents=True, exist_ok=True)
    for s in ("aerial_sfm", "train_splat"):
        m = pipeline.marker_path(base, s)
        if m.exists():
            shutil.copy2(m, pipeline.marker_path(job, s))


def seed_matches(job: pipeline.Job, others: list[pipeline.Job]) -> None:
    """Copy the per-view match files of other configurations (same views: match_view skips them)."""
    job.dir("matches").mkdir(parents=True, exist_ok=True)
    for o in others:
        for p in sorted(o.dir("matches").glob("*.h5")):
            dst = job.dir("matches") / p.name
            if not dst.exists():
                shutil.copy2(p, dst)


def truth_alignment(scene: Path, sparse: Path) -> tuple[float, np.ndarray, np.ndarray]:
    """truth_from_model similarity fitted on the aerial camera centres."""
    from services.colmap_model import read_model
    from services.synth import similarity_fit as _kabsch

    _, est = read_model(sparse)
    _, gt = read_model(scene / "gt" / "sparse")
    names = sorted(n for n in est if n in gt and n.startswith("aerial/"))
    return _kabsch(np.array([est[n].center for n in names]), np.array([gt[n].center for n in names]), True)


def aerial_truth_depths(gt, sparse: Path, width: int) -> list[tuple]:
    """(camera `width` px wide, pose, the truth's z-depth there) of every image of the aerial model
    `sparse`, from a GroundTruthRenderer `gt` aligned to it."""
    from services.colmap_model import read_model
    from services.geometry import scaled_camera

    cams, poses = read_model(sparse)
    out = []
    for n, p in sorted(poses.items()):
        c = scaled_camera(cams[n], width)
        out.append((c, p, gt.render(c, p)[1]))
    return out


def aerial_seen_count(X: np.ndarray, aerial: list[tuple]) -> np.ndarray:
    """How many of the aerial images (aerial_truth_depths) see each point X (N, 3) of the true surface:
    it projects into the image and the truth's depth there is within 3% + 0.2 m of it (not hidden)."""
    seen = np.zeros(len(X), int)
    for ca, pa, da in aerial:
        uv, z = pa.project(ca.K, X)
        ok = (z > 0) & (uv >= 0).all(1) & (uv[:, 0] < ca.width - 1) & (uv[:, 1] < ca.height - 1)
        i = np.nonzero(ok)[0]
        zs = da[uv[i, 1].astype(int), uv[i, 0].astype(int)]
        seen[i[np.abs(zs - z[i]) <= 0.03 * z[i] + 0.2]] += 1
    return seen


def aerial_observable(scene: Path, sparse: Path, width: int = 160, min_images: int = 2) -> dict[str, float]:
    """Per ground image, the fraction of what it sees (the truth's depth at its true pose, `width` px)
    that at least `min_images` aerial images of the model see too (the truth's depth at their poses,
    within 3% + 0.2 m): what any view rendered from the aerial images can show of it. Perfect views
    render the truth, also where no aerial image looks."""
    from services.colmap_model import Pose, read_model
    from services.geometry import scaled_camera
    from services.views import GroundTruthRenderer

    gt = GroundTruthRenderer(scene, sparse)
    aerial = aerial_truth_depths(gt, sparse, 3 * width)
    s, R, t = truth_alignment(scene, sparse)  # truth = s R model + t
    gcams, gposes = read_model(scene / "gt" / "sparse")
    out = {}
    for g in sorted(n for n in gposes if n.startswith("ground/")):
        P = gposes[g]
        pose = Pose(P.R @ R, (P.R @ t + P.t) / s)  # the true pose in the model frame
        c = scaled_camera(gcams[g], width)
        d = gt.render(c, pose)[1]
        v, u = np.nonzero(d > 0)
        X = pose.unproject(c.K, np.stack([u + 0.5, v + 0.5], 1), d[v, u].astype(float))
        seen = aerial_seen_count(X, aerial)
        out[g] = float((seen >= min_images).mean()) if len(X) else 0.0
    return out


def pnp_accuracy(scene: Path, job: pipeline.Job) -> dict:
    """The reducer's accepted ground poses against the true centres (model frame aligned to the truth)."""
    from services.colmap_model import read_model

    s, R, t = truth_alignment(scene, job.sfm.sparse)
    _, gt = read_model(scene / "gt" / "sparse")
    doc = json.loads((job.transfer.ground_poses).read_text())["images"]
    errs = []
    for g, r in doc.items():
        if r.get("accepted") and g in gt:
            c = s * R @ np.asarray(r["center"], float) + t
            errs.append(float(np.linalg.norm(c - gt[g].center)))
    n_ground = sum(n.startswith("ground/") for n in gt)
    return {
        "accepted": f"{len(errs)}/{n_ground}",
        "mean_m": float(np.mean(errs)) if errs else None,
        "median_m": float(np.median(errs)) if errs else None,
        "max_m": float(np.max(errs)) if errs else None,
    }


def direct_same_budget(scene: Path, base: pipeline.Job, out: Path) -> Path:
    """Direct ALIKED+LightGlue on the POS pairs with midview's features (its keypoint budget)."""
    from services.matching import direct
    from services.matching import pairs as pairs_mod
    from services.matching.views import feature_conf
    from shared.images import list_images

    path = out / "direct-aliked-lightglue-same-budget.h5"
    if path.exists():
        return path
    names = list_images(scene / "images")
    pairs = pairs_mod.get_pairs(pairs_mod.confs["pos"], names, scene / "pos.csv", scene / "cameras.json")
    fconf = feature_conf(base.match_conf())
    conf = {**direct.confs["aliked-lightglue"], "name": "direct-alg-same-budget", "features": fconf}
    cache = out / "direct-features"
    cache.mkdir(parents=True, exist_ok=True)
    shared = base.features_path
    if shared.exists() and not (cache / shared.name).exists():
        shutil.copy2(shared, cache / shared.name)  # reuse midview's cached features, extract the rest
    tmp = path.with_suffix(".tmp.h5")
    direct.main(conf, scene, pairs, tmp, cache)
    tmp.replace(path)
    return path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--preset", default="isprs", help="synthetic preset (small for continuity)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--scene", type=Path, help="a rendered scene folder (default: runs/bench/scene-<preset>-seed<seed>)"
    )
    ap.add_argument(
        "--renderers",
        default="gt,splat",
        help="comma-separated: gt (perfect views), splat (the product: the 3DGS, views coloured from the"
        " aerial images), 3dgs (the 3DGS's own colour)",
    )
    ap.add_argument(
        "--planners", default="paper,ground-aware,both", help="comma-separated: paper, ground-aware, both"
    )
    ap.add_argument("--profile", default="cpu", help="job profile whose defaults the options not given take")
    ap.add_argument("--views", type=int, help="views per ground image (default: the profile's)")
    ap.add_argument("--max-keypoints", type=int, help="ALIKED keypoints per image (default: the profile's)")
    ap.add_argument(
        "--matchers",
        default="aliked-lightglue",
        help="comma-separated: aliked-lightglue, sift (views' matcher)",
    )
    ap.add_argument("--sift-keypoints", type=int, default=8192, help="SIFT features per image (matcher sift)")
    ap.add_argument("--splat-steps", type=int, help="3DGS steps (default: the profile's)")
    ap.add_argument("--splat-max-width", type=int, help="3DGS training width (default: the profile's)")
    ap.add_argument(
        "--block-steps",
        type=int,
        default=0,
        help="train_blocks: 3DGS steps per block at the source resolution for the splat renderer (0: none)",
    )
    ap.add_argument(
        "--splat-set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="3DGS conf entry (services.splat confs), repeatable: --splat-set depth_lambda=0.05",
    )
    ap.add_argument(
        "--view-set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="viewpoint conf entry (services.views confs), repeatable: --view-set ground.max_width=640",
    )
    ap.add_argument(
        "--match-set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="matching conf entry (services.matching.views confs), repeatable:"
        " --match-set render_max_keypoints=2048",
    )
    ap.add_argument(
        "--render-set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="views' rendering conf entry (services.views.rendering), repeatable: --render-set colour=splat",
    )
    ap.add_argument("--torch-threads", type=int, default=1)
    ap.add_argument("--no-sfm", action="store_true", help="skip the combined reconstructions")
    ap.add_argument("--adopt-sfm", type=Path, help="an aerial SfM output folder to use instead of running it")
    ap.add_argument("--adopt-splat", type=Path, help="a 3DGS training folder (trained on --adopt-sfm) to use")
    ap.add_argument("--out", type=Path, help="output folder (default: runs/bench/method-<preset>-seed<seed>)")
    ap.add_argument(
        "--json", type=Path, help="also write the figures here (docs/results/method-<preset>.json)"
    )
    args = ap.parse_args(argv)
    setup_logging("INFO")
    from rich.console import Console
    from rich.table import Table

    from services.evaluation import evaluate_matches, evaluate_sfm, keypoint_bound, print_summary_table

    console = Console(width=None if sys.stdout.isatty() else 150)
    tag = f"{args.preset}-seed{args.seed}"
    scene = args.scene or ROOT / "runs" / "bench" / f"scene-{tag}"
    out = args.out or ROOT / "runs" / "bench" / f"method-{tag}"
    out.mkdir(parents=True, exist_ok=True)
    textures = DEFAULT_TEXTURES if DEFAULT_TEXTURES.is_dir() else None
    ensure_scene(args.preset, args.seed, scene, textures)
    renderers = [r.strip() for r in args.renderers.split(",") if r.strip()]
    planners = [p.strip() for p in args.planners.split(",") if p.strip()]
    planners = [p for p in ("paper", "ground-aware", "both") if p in planners]  # "both" last
    matchers = [m.strip() for m in args.matchers.split(",") if m.strip()]
    given = {
        "views_per_ground_image": args.views,
        "max_keypoints": args.max_keypoints,
        "splat_steps": args.splat_steps,
        "splat_max_width": args.splat_max_width,
    }
    # the job profile's defaults (what `midview run` and the demo run) but for the options given
    options = {"profile": args.profile, "seed": args.seed}
    options.update({k: v for k, v in given.items() if v is not None})
    settings = {
        **pipeline.parse_settings_overrides(
            args.splat_set, args.view_set, args.match_set, rendering=args.render_set
        ),
        "torch_threads": args.torch_threads,
        "scene": str(scene),
    }
    timings: dict[str, float] = {}
    # the base job: aerial SfM (+ 3DGS)
    t0 = time.perf_counter()
    base = make_job(
        out / "base",
        scene,
        {**options, "stages": ["aerial_sfm", "train_splat"]},
        {**settings, "renderer": "splat" if {"splat", "3dgs"} & set(renderers) else "gt"},
    )
    if args.adopt_sfm and not pipeline.is_done(base, "aerial_sfm"):
        dst = base.dir("sfm")
        shutil.rmtree(dst, ignore_errors=True)
        shutil.copytree(args.adopt_sfm, dst, symlinks=True)
        pipeline.write_job_cameras(base)
        pipeline.mark_done(base, "aerial_sfm", {"from": str(args.adopt_sfm)})
    if args.adopt_splat and not pipeline.is_done(base, "train_splat"):
        dst = base.dir("splat")
        shutil.rmtree(dst, ignore_errors=True)
        shutil.copytree(args.adopt_splat, dst)
        pipeline.mark_done(base, "train_splat", {"from": str(args.adopt_splat)})
    res = pipeline.run(base, progress=lambda s, f, m: logger.info("[%s] %3.0f%% %s", s, 100 * f, m))
    timings["base"] = time.perf_counter() - t0
    for s, r in res.items():
        timings[f"base:{s}"] = float(r.get("seconds", 0.0))
    jobs: dict[tuple[str, str, str], pipeline.Job] = {}
    stages = ["plan_views", "train_blocks", "render_views", "match_views", "reduce"] + (
        [] if args.no_sfm else ["combined_sfm"]
    )
    if not args.block_steps:
        stages.remove("train_blocks")
    for mt in matchers:
        for r in renderers:
            for p in planners:
                name = config_name(r, p, mt, args.block_steps)
                keypoints = base.options.max_keypoints if mt == "aliked-lightglue" else args.sift_keypoints
                job = make_job(
                    out / name,
                    scene,
                    {
                        **options,
                        "view_planner": p,
                        "matcher": mt,
                        "max_keypoints": keypoints,
                        "block_steps": args.block_steps,
                        "stages": ["aerial_sfm", "train_splat", *stages],
                    },
                    renderer_settings(settings, r),
                )
                link_base(job, base)
                if p == "both":
                    same = [jobs[(r, q, mt)] for q in ("paper", "ground-aware") if (r, q, mt) in jobs]
                    seed_matches(job, same)
                t0 = time.perf_counter()
                res = pipeline.run(
                    job,
                    stages=stages,
                    progress=lambda s, f, m, n=name: logger.info("[%s %s] %3.0f%% %s", n, s, 100 * f, m),
                )
                # each stage's seconds as its marker recorded them (also when this run found it up to
                # date), the config's total their sum: a rerun that only redoes one stage reports the
                # whole method's time, with this run's own wall time beside it
                for s, rr in res.items():
                    timings[f"{name}:{s}"] = float(rr.get("seconds", 0.0))
                timings[name] = sum(timings[f"{name}:{s}"] for s in res)
                timings[f"{name}:this-run"] = time.perf_counter() - t0
                jobs[(r, p, mt)] = job
    # baselines
    files: dict[str, Path] = {}
    bl = ROOT / "runs" / "bench" / f"baselines-{tag}"
    for label, f in (
        ("direct SIFT (8192, 1600 px)", "sift.h5"),
        ("direct ALIKED+LightGlue (2048)", "aliked-lightglue.h5"),
    ):
        if (bl / f).exists():
            files[label] = bl / f
    t0 = time.perf_counter()
    files[f"direct ALIKED+LightGlue ({base.options.max_keypoints})"] = direct_same_budget(scene, base, out)
    timings["direct same budget"] = time.perf_counter() - t0
    for (r, p, mt), job in jobs.items():
        files[f"midview {config_name(r, p, mt, args.block_steps).replace('-', ' ', 1)}"] = (
            job.transfer.matches
        )
    rows = []
    for label, path in files.items():
        s = evaluate_matches(
            scene, path, out / "eval" / label.replace(" ", "_").replace("(", "").replace(")", "")
        )
        s["method"] = label
        s["bound"] = keypoint_bound(scene, path)
        rows.append(s)
    print_summary_table(
        rows, title=f"Aerial-ground matches, {args.preset} (means over the co-visible pairs)", console=console
    )
    # what any matcher could reach with each file's keypoints (services.evaluation.keypoint_bound)
    bt = Table(title="Keypoint bound: the most GT-correct matches possible with each method's keypoints")
    for col in ("method", "GT-correct", "bound", "of the bound", "NMP", "NMP bound"):
        bt.add_column(col, justify="left" if col == "method" else "right")
    for s in rows:
        b = s["bound"]
        frac = s["total_gt_correct"] / b["total"] if b["total"] else 0.0
        bt.add_row(
            s["method"],
            str(s["total_gt_correct"]),
            str(b["total"]),
            f"{frac:.2f}",
            str(s["nmp"]),
            str(b["nmp"]),
        )
    console.print(bt)
    sfm_rows = {}
    table = Table(
        title="Ground cameras: PnP poses of the reducer and the combined reconstruction (errors in m)"
    )
    for col in (
        "config",
        "views",
        "PnP accepted",
        "PnP err mean",
        "PnP err max",
        "NRI aerial",
        "NRI ground",
        "within 0.5 m",
        "ground abs err med",
        "p90",
        "max",
        "aerial-aligned med",
        "max",
        "N3P",
    ):
        table.add_column(col, justify="left" if col == "config" else "right")
    for (r, p, mt), job in jobs.items():
        pa = pnp_accuracy(scene, job)
        label = config_name(r, p, mt, args.block_steps).replace("-", " ", 1)
        nv = len(json.loads((job.views.doc).read_text())["views"])
        row = {"pnp": pa, "num_views": nv}
        cells = [label, str(nv), pa["accepted"], _f(pa["mean_m"]), _f(pa["max_m"])]
        if not args.no_sfm:
            ev = evaluate_sfm(scene, job.combined.sparse, out / "eval" / f"sfm-{job.root.name}")
            ps = ev["per_set"]
            row["sfm"] = ev
            ab, aa = ps["ground"]["absolute_error"], ps["ground"]["aerial_aligned_error"]
            cells += [
                f"{ps['aerial']['num_registered']}/{ps['aerial']['num_gt']}",
                f"{ps['ground']['num_registered']}/{ps['ground']['num_gt']}",
                str(within(ev)),
                _f(ab["median"]),
                _f(ab["p90"]),
                _f(ab["max"]),
                _f(aa["median"]),
                _f(aa["max"]),
                str(ev["num_points3D"]),
            ]
        else:
            cells += ["-"] * 9
        table.add_row(*cells)
        sfm_rows[label] = row
    console.print(table)
    ref = next((s for s in rows if s["method"].startswith("direct ALIKED+LightGlue (2048")), None)
    if ref is not None:
        for s in rows:
            if s["method"].startswith("midview"):
                console.print(
                    f"{s['method']}: GT-correct {s['total_gt_correct']} = "
                    f"{s['total_gt_correct'] / max(ref['total_gt_correct'], 1):.2f} x "
                    "direct ALIKED+LightGlue (2048); "
                    f"pooled precision {s['pooled_precision']:.3f}; NMP {s['nmp']} vs {ref['nmp']}"
                )
    console.print("timings (s): " + json.dumps({k: round(v, 1) for k, v in timings.items()}))
    (out / "method.json").write_text(
        json.dumps(
            {
                "scene": str(scene),
                "options": options,
                "matches": rows,
                "cameras": sfm_rows,
                "timings": timings,
            },
            indent=1,
            default=str,
        )
    )
    console.print(f"report: {out / 'method.json'}")
    if args.json:
        doc = results_doc(rows, sfm_rows, timings, argv)
        if not args.no_sfm and jobs:
            add_observable(doc, aerial_observable(scene, next(iter(jobs.values())).sfm.sparse), sfm_rows)
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(doc, indent=1))
        console.print(f"figures: {args.json}")
    return 0


def add_observable(
    doc: dict, observable: dict[str, float], sfm_rows: dict, min_fraction: float = 0.5
) -> None:
    """The figures with the aerial-observability bound: per ground image its fraction (aerial_observable),
    the number at least min_fraction observable, and per method how many of those it put within 0.5 m."""
    keep = {g for g, f in observable.items() if f >= min_fraction}
    doc["figures"]["ground_aerial_observable"] = {g: round(f, 3) for g, f in observable.items()}
    doc["figures"]["ground_observable_total"] = len(keep)
    for label, row in sfm_rows.items():
        ev = row.get("sfm")
        if not ev:
            continue
        key, planner = method_key("midview " + label)
        n = sum(
            r["set"] == "ground" and r["name"] in keep and r.get("absolute_error", np.inf) <= 0.5
            for r in ev["per_image"]
        )
        for k in (key, f"{key}-{planner}"):
            if k in doc["figures"] and doc["figures"][k].get("planner") == planner:
                doc["figures"][k]["ground_observable_within_0_5m"] = n


def within(ev: dict, metres: float = 0.5) -> int:
    """Ground images of an evaluate_sfm summary within `metres` of the truth in absolute terms."""
    if not ev.get("georef"):
        return 0
    return sum(r["set"] == "ground" and r.get("absolute_error", np.inf) <= metres for r in ev["per_image"])


def method_key(label: str) -> tuple[str, str | None]:
    """The figures' name of a row ("midview splat both" -> ("midview", "both")), planner or None."""
    if label.startswith("midview"):
        parts = label.split()
        kind = {"gt": "perfect-views", "3dgs": "midview-3dgs-colour"}.get(parts[1], "midview")
        return kind + "".join(f"-{x}" for x in parts[3:]), parts[2]
    if label.startswith("direct SIFT"):
        return "direct-sift", None
    if label.startswith("direct ALIKED+LightGlue (2048"):
        return "direct-aliked-lightglue-2048", None
    return "direct-aliked-lightglue", None


def results_doc(rows: list[dict], sfm_rows: dict, timings: dict, argv: list[str] | None) -> dict:
    """docs/results/method-<preset>.json: the command, the commit and, per method, the figures."""
    import subprocess

    commit = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, cwd=ROOT).stdout
    figures: dict[str, dict] = {}
    for s in rows:
        key, planner = method_key(s["method"])
        f = {
            "gt_correct": s["total_gt_correct"],
            "pooled_precision": s["pooled_precision"],
            "nmp": s["nmp"],
            "num_pairs": s["num_pairs"],
        }
        if planner is not None:
            config = s["method"].split(" ", 1)[1]
            ev = sfm_rows.get(config, {}).get("sfm")
            f["planner"] = planner
            f["seconds"] = timings.get(config.replace(" ", "-", 1))
            if ev:
                g = ev["per_set"]["ground"]
                f.update(
                    ground_total=g["num_gt"],
                    ground_registered=g["num_registered"],
                    ground_within_0_5m=within(ev),
                    ground_abs_error_m={k: g["absolute_error"][k] for k in ("median", "p90", "max")},
                    ground_aerial_aligned_error_m={
                        k: g["aerial_aligned_error"][k] for k in ("median", "p90", "max")
                    },
                    aerial_abs_error_m={
                        k: ev["per_set"]["aerial"]["absolute_error"][k] for k in ("median", "p90", "max")
                    },
                )
            # "midview" / "perfect-views": the "both" planner's (else the first run); each also by planner
            if key not in figures or planner == "both":
                figures[key] = f
            key = f"{key}-{planner}"
        figures[key] = f
    return {
        "command": "python bench/method.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "commit": commit.strip(),
        "figures": figures,
        "timings_s": timings,
    }


def renderer_settings(settings: dict, renderer: str) -> dict:
    """A job's settings for a bench renderer: "3dgs" is the splat renderer with the 3DGS's own colour."""
    if renderer != "3dgs":
        return {**settings, "renderer": renderer}
    return {**settings, "renderer": "splat", "views": {**settings.get("views", {}), "colour": "splat"}}


def config_name(renderer: str, planner: str, matcher: str, block_steps: int = 0) -> str:
    """The job folder of a configuration: RENDERER-PLANNER, with -sift for the SIFT matcher and -blocksN
    for the splat renderer with blocks trained N steps."""
    blocks = f"-blocks{block_steps}" if block_steps and renderer in ("splat", "3dgs") else ""
    return f"{renderer}-{planner}" + ("" if matcher == "aliked-lightglue" else f"-{matcher}") + blocks


def _f(v) -> str:
    return "-" if v is None else f"{v:.3f}"


if __name__ == "__main__":
    sys.exit(main())
