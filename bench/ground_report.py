"""Why each ground image of a method run is in or out: one row per ground image of a job folder.

    python bench/ground_report.py --scene runs/bench/scene-small-walk-seed0 \\
        --job runs/bench/m-walk/splat-both --json runs/ground-report.json

Per ground image: the reducer's PnP (its 2D-3D correspondences and inliers, accepted or not, its error
against the truth after aligning the aerial model by its cameras), the combined SfM's registration (by
the mapper or at the PnP pose, its absolute error against the truth) or the reason it gives, and the
image's verified ground-ground pairs (the largest, and how many lead to a registered image). Each image
gets one cause:

- `within`: registered within `--metres` (absolute);
- `off`: registered farther off;
- `dropped`: registered, then dropped (ill-determined, or far from its POS);
- `ground-only`: verified ground-ground pairs of at least `--min-pair` matches, but too few of its
  matches reach the model's points (no aerial tie strong enough, no registered neighbour sharing them);
- `unmatched`: no verified pair of `--min-pair` matches.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import Counter
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
for p in (ROOT, ROOT / "bench"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

from method import truth_alignment  # noqa: E402

from services.colmap_model import read_model  # noqa: E402
from services.evaluation import evaluate_sfm  # noqa: E402
from services.pipeline import Job  # noqa: E402

CAUSES = ("within", "off", "dropped", "ground-only", "unmatched")


def ground_ground(report: dict, registered: set[str], min_pair: int) -> dict[str, dict]:
    """Per ground image: its largest verified ground-ground pair and its registered partners (pairs of
    at least min_pair inliers), from the combined report's `ground_pairs`."""
    out: dict[str, dict] = {}
    for key, rec in report.get("ground_pairs", {}).items():
        a, b = key.split(" ")
        n = int(rec.get("inliers", 0)) if rec.get("accepted") else 0
        for g, h in ((a, b), (b, a)):
            d = out.setdefault(g, {"largest_pair": 0, "registered_partners": 0})
            d["largest_pair"] = max(d["largest_pair"], n)
            d["registered_partners"] += int(n >= min_pair and h in registered)
    return out


def ground_pair_truth(scene: Path, database: Path, report: dict) -> dict[str, dict]:
    """Per verified ground-ground pair of the combined report ("g0 g1"): its inlier matches in the combined
    database and how many of them are GT-correct (within 3 px through the true depth, both ways)."""
    import pycolmap

    from services.evaluation.common import read_gt_model
    from services.evaluation.matches import gt_correct_mask
    from services.synth import read_depth

    cams, poses = read_gt_model(scene)
    out: dict[str, dict] = {}
    with pycolmap.Database.open(str(database)) as db:
        ids = {im.name: im.image_id for im in db.read_all_images()}
        for key, rec in report.get("ground_pairs", {}).items():
            if not rec.get("accepted"):
                continue
            a, b = key.split(" ")
            m = np.asarray(db.read_two_view_geometry(ids[a], ids[b]).inlier_matches).reshape(-1, 2)
            kp = [np.asarray(db.read_keypoints(ids[n]))[:, :2] for n in (a, b)]
            ok = gt_correct_mask(
                kp[0][m[:, 0]], kp[1][m[:, 1]], cams[a], poses[a], read_depth(scene, a),
                cams[b], poses[b], read_depth(scene, b),
            )  # fmt: skip
            out[key] = {"inliers": len(m), "gt_correct": int(ok.sum())}
            if "surface" in rec:  # the check against the aerial surface (services.sfm.combined.surface)
                s = rec["surface"]
                out[key]["surface"] = {
                    k: s.get(k) for k in ("accepted", "offset_m", "limit_m", "pnp_inliers", "points")
                }
    return out


REFUSAL_KINDS = {  # the start of a refused pair's reason (services.sfm.combined.database) -> its kind
    "an uncalibrated fundamental matrix": "calibrated",
    "against the aerial surface": "surface",
    "against the other pairs": "consistency",
    "relative rotation": "pos",
    "baseline direction": "pos",
}


def refusal_kind(reason: str | None) -> str:
    """The check that refused a ground-ground pair, from its reason: calibrated, surface, consistency,
    pos (its relative pose against the POS), attitudes (its rotation against the images' aerial-tied
    attitudes, the POS agreeing), or few (too few matches or inliers)."""
    first = (reason or "").split("; ")[0]
    if first.startswith("relative rotation") and "aerial-tied attitudes" in first:
        return "attitudes"
    for start, kind in REFUSAL_KINDS.items():
        if first.startswith(start):
            return kind
    return "few"


def refused_pair_truth(scene: Path, job_root: Path, report: dict, min_pair: int) -> dict[str, dict]:
    """Per refused ground-ground pair of the combined report with at least `min_pair` inliers: the pair
    matched again with the job's features and matcher, verified by the essential matrix and the POS alone
    (none of the checks after them), and how many of those inliers are GT-correct; with the refusing
    check's kind. What the checks cost in true pairs, which the verified pairs alone cannot show."""
    from services.colmap_model import read_cameras_json
    from services.conf import merge_conf
    from services.evaluation.common import read_gt_model
    from services.evaluation.matches import gt_correct_mask
    from services.matching import match_features
    from services.reduce import ground_priors
    from services.sfm.combined.confs import default_conf
    from services.sfm.combined.database import ground_features, verify_ground_pair
    from services.synth import read_depth

    job = Job.load(job_root)
    conf = {**merge_conf(default_conf, job.combined_conf())["ground_pairs"], "require_calibrated": False}
    refused = {
        k: r for k, r in report.get("ground_pairs", {}).items()
        if not r.get("accepted") and int(r.get("inliers", 0)) >= min_pair
    }  # fmt: skip
    if not refused:
        return {}
    priors, prior_std = ground_priors(job.pos, job.sfm.dir / "georef.json")
    names = sorted({n for k in refused for n in k.split(" ")})
    feats = ground_features(names, job.features_path, job.image_dir, job.match_conf())
    camera = read_cameras_json(job.cameras)["ground"]
    cams, poses = read_gt_model(scene)
    out: dict[str, dict] = {}
    for key, rec in sorted(refused.items()):
        a, b = key.split(" ")
        m, _ = match_features(feats[a], feats[b], job.match_conf()["matcher"])
        k0, k1 = (np.asarray(feats[n]["keypoints"])[:, :2] for n in (a, b))
        args = (camera, priors[a], priors[b], prior_std[a], prior_std[b], conf)
        inl, _ = verify_ground_pair(k0, k1, m, *args)
        ok = gt_correct_mask(
            k0[inl[:, 0]], k1[inl[:, 1]], cams[a], poses[a], read_depth(scene, a),
            cams[b], poses[b], read_depth(scene, b),
        ) if len(inl) else np.zeros(0, bool)  # fmt: skip
        out[key] = {"kind": refusal_kind(rec.get("reason")), "inliers": len(inl), "gt_correct": int(ok.sum())}
    return out


def refusals_by_kind(pairs: dict[str, dict]) -> dict[str, dict[str, int]]:
    """Per refusing check: the refused pairs that the essential matrix and the POS alone verify, those
    of them without a GT-correct inlier, and those with at least half of their inliers GT-correct."""
    out: dict[str, dict[str, int]] = {}
    for p in pairs.values():
        if not p["inliers"]:
            continue
        d = out.setdefault(p["kind"], {"verified_without": 0, "false": 0, "mostly_correct": 0})
        d["verified_without"] += 1
        d["false"] += int(p["gt_correct"] == 0)
        d["mostly_correct"] += int(2 * p["gt_correct"] >= p["inliers"])
    return out


def surface_verdicts(pairs: dict[str, dict]) -> dict[str, int]:
    """The surface check's verdicts on verified pairs against the truth (a pair with no GT-correct match
    is false): true pairs kept and refused, false pairs kept and refused (pairs it did not judge apart)."""
    out = {"true_kept": 0, "true_refused": 0, "false_kept": 0, "false_refused": 0, "not_judged": 0}
    for p in pairs.values():
        s = p.get("surface")
        if s is None or s.get("offset_m") is None and s.get("accepted"):
            out["not_judged"] += 1
            continue
        truth = "true" if p["gt_correct"] > 0 else "false"
        out[f"{truth}_{'kept' if s['accepted'] else 'refused'}"] += 1
    return out


def cause(row: dict, metres: float, min_pair: int) -> str:
    """One of CAUSES for a row of ground_rows."""
    if row["registered"]:
        return "within" if row["error_m"] is not None and row["error_m"] <= metres else "off"
    if "dropped" in (row["reason"] or ""):
        return "dropped"
    return "ground-only" if row["largest_pair"] >= min_pair else "unmatched"


def ground_rows(
    scene: Path, job_root: Path, out: Path, metres: float = 0.5, min_pair: int = 15
) -> list[dict]:
    """The rows (module docstring) of the job folder `job_root` against the synthetic scene `scene`."""
    job = Job.load(job_root)
    s, R, t = truth_alignment(scene, job.sfm.sparse)
    _, gt = read_model(scene / "gt" / "sparse")
    pnp = json.loads(job.transfer.ground_poses.read_text())["images"]
    report = json.loads(job.combined.report.read_text())
    ev = evaluate_sfm(scene, job.combined.sparse, out)
    abs_err = {r["name"]: r.get("absolute_error") for r in ev["per_image"]}
    registered = {g for g, r in report["ground"].items() if r.get("registered")}
    gg = ground_ground(report, registered, min_pair)
    rows = []
    for g in sorted(n for n in gt if n.startswith("ground/")):
        p, r = pnp.get(g, {}), report["ground"].get(g, {})
        centre = p.get("center")
        row = {
            "name": g,
            "pnp_accepted": bool(p.get("accepted")),
            "pnp_correspondences": int(p.get("num_correspondences", 0)),
            "pnp_inliers": int(p.get("num_inliers", 0)),
            "pnp_error_m": None
            if centre is None
            else float(np.linalg.norm(s * R @ np.asarray(centre, float) + t - gt[g].center)),
            "registered": bool(r.get("registered")),
            "registered_by": r.get("registered_by"),
            "error_m": abs_err.get(g),
            "reason": r.get("reason"),
            **gg.get(g, {"largest_pair": 0, "registered_partners": 0}),
        }
        row["cause"] = cause(row, metres, min_pair)
        rows.append(row)
    return rows


def summary(rows: list[dict]) -> dict:
    """{cause: count} and {cause: [names]} over the rows."""
    counts = Counter(r["cause"] for r in rows)
    return {
        "counts": {c: counts.get(c, 0) for c in CAUSES},
        "images": {c: [r["name"] for r in rows if r["cause"] == c] for c in CAUSES if counts.get(c)},
    }


def _f(v, fmt: str = "{:.2f}") -> str:
    return "-" if v is None else fmt.format(v)


def print_rows(rows: list[dict]) -> None:
    from rich.console import Console
    from rich.table import Table

    table = Table(title="ground images: in or out, and why")
    for c in ("image", "cause", "PnP corr/inl", "PnP ok", "PnP err m", "by", "err m", "gg pair", "reg nb"):
        table.add_column(c)
    for r in rows:
        table.add_row(
            Path(r["name"]).stem,
            r["cause"],
            f"{r['pnp_correspondences']}/{r['pnp_inliers']}",
            "yes" if r["pnp_accepted"] else "no",
            _f(r["pnp_error_m"]),
            r["registered_by"] or "-",
            _f(r["error_m"]),
            str(r["largest_pair"]),
            str(r["registered_partners"]),
        )
    console = Console(width=max(Console().width, 120))
    console.print(table)
    console.print(summary(rows)["counts"])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", type=Path, required=True, help="the synthetic scene folder (gt/)")
    ap.add_argument("--job", type=Path, required=True, help="a job folder of bench/method.py")
    ap.add_argument("--metres", type=float, default=0.5)
    ap.add_argument("--min-pair", type=int, default=15, help="verified matches of a ground-ground pair")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument(
        "--refused", action="store_true", help="also match the refused pairs again and judge them (minutes)"
    )
    args = ap.parse_args(argv)
    rows = ground_rows(args.scene, args.job, args.job / "eval-ground-report", args.metres, args.min_pair)
    print_rows(rows)
    combined = Job.load(args.job).combined.dir
    report = json.loads((combined / "report.json").read_text())
    pairs = ground_pair_truth(args.scene, combined / "database.db", report)
    false = sorted(k for k, p in pairs.items() if p["gt_correct"] == 0)
    print(f"verified ground-ground pairs: {len(pairs)}, without a GT-correct match: {len(false)} {false}")
    verdicts = surface_verdicts(pairs)
    print(f"the surface check on them (pairs it refused are kept when it is not enforced): {verdicts}")
    refused = refused_pair_truth(args.scene, args.job, report, args.min_pair) if args.refused else {}
    if args.refused:
        by_check = refusals_by_kind(refused)
        print(f"refused pairs the essential matrix and the POS alone verify, by check: {by_check}")
    if args.json:
        doc = {"command": "python bench/ground_report.py " + " ".join(argv or sys.argv[1:])}
        extra = {"ground_pairs": pairs, "ground_pairs_without_correct": false, "surface_verdicts": verdicts}
        if args.refused:
            extra |= {"refused_pairs": refused, "refusals_by_check": refusals_by_kind(refused)}
        args.json.write_text(json.dumps({**doc, **summary(rows), **extra, "per_image": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
