"""Figures of an aerial reconstruction (NRI, N3P, reprojection error, track length, georeferencing
residuals, stage times) and why images did not register, from the model and its database."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pycolmap


def image_graph(database_path: str | Path, min_inliers: int = 15) -> dict[str, dict]:
    """Per image name: keypoints, verified pairs (>= min_inliers) and their largest inlier count."""
    db = pycolmap.Database.open(str(database_path))
    try:
        names = {im.image_id: im.name for im in db.read_all_images()}
        out = {
            n: {"keypoints": int(db.num_keypoints_for_image(i)), "pairs": 0, "max_inliers": 0}
            for i, n in names.items()
        }
        pair_ids, counts = db.read_two_view_geometry_num_inliers()
    finally:
        db.close()
    for pid, n in zip(pair_ids, counts, strict=True):
        if n < min_inliers:
            continue
        for i in pycolmap.pair_id_to_image_pair(pid):
            g = out[names[i]]
            g["pairs"] += 1
            g["max_inliers"] = max(g["max_inliers"], int(n))
    return out


def unregistered_reason(name: str, graph: dict[str, dict], other_models: dict[str, int]) -> str:
    """A short explanation of why an image is missing from the chosen model."""
    g = graph.get(name)
    if g is None:
        return "not in the database (features could not be extracted)"
    if g["keypoints"] == 0:
        return "no features detected"
    if g["pairs"] == 0:
        return f"no geometrically verified image pair ({g['keypoints']} features)"
    if name in other_models:
        return f"registered in a separate, smaller model #{other_models[name]} (no link to the main one)"
    return f"registration failed ({g['pairs']} verified pairs, best {g['max_inliers']} inliers)"


def model_stats(rec: pycolmap.Reconstruction) -> dict:
    """N3P, mean reprojection error (px), mean track length, mean observations per registered image."""
    return {
        "num_points3D": int(rec.num_points3D()),
        "mean_reprojection_error_px": float(rec.compute_mean_reprojection_error()),
        "mean_track_length": float(rec.compute_mean_track_length()),
        "mean_observations_per_image": float(rec.compute_mean_observations_per_reg_image()),
    }


def camera_summary(rec: pycolmap.Reconstruction) -> list[dict]:
    return [
        {
            "camera_id": int(c.camera_id),
            "model": c.model.name,
            "width": int(c.width),
            "height": int(c.height),
            "params": [float(p) for p in c.params],
        }
        for c in rec.cameras.values()
    ]


def build_report(
    rec: pycolmap.Reconstruction,
    names: list[str],
    database_path: str | Path,
    models: dict[int, pycolmap.Reconstruction],
    chosen: int,
    georef: dict | None,
    timings: dict[str, float],
    extra: dict | None = None,
    min_inliers: int = 15,
) -> dict:
    """The report.json document of a reconstruction."""
    registered = {im.name for im in rec.images.values() if im.has_pose}
    other = {im.name: k for k, m in models.items() if k != chosen for im in m.images.values() if im.has_pose}
    graph = image_graph(database_path, min_inliers)
    missing = sorted(set(names) - registered)
    return {
        "num_images": len(names),
        "num_registered": len(registered & set(names)),
        "NRI": f"{len(registered & set(names))}/{len(names)}",
        "unregistered": [{"name": n, "reason": unregistered_reason(n, graph, other)} for n in missing],
        "num_models": len(models),
        "model_sizes": sorted((int(m.num_reg_images()) for m in models.values()), reverse=True),
        **model_stats(rec),
        "cameras": camera_summary(rec),
        "georef": georef,
        "timings_s": {k: round(v, 3) for k, v in timings.items()},
        **(extra or {}),
    }


def write_report(path: str | Path, report: dict) -> Path:
    path = Path(path)
    path.write_text(json.dumps(report, indent=1, default=_json_default))
    return path


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"{type(o).__name__} is not JSON serialisable")


def compare_with_truth(out_dir: str | Path, scene_dir: str | Path, image_set: str = "aerial") -> dict:
    """Camera positions of a georeferenced SfM output (out_dir: sparse/, georef.json) against the true
    poses of a synthetic scene (gt/sparse, gt/scene.json), both taken to WGS84 and then to the scene's
    frame: absolute errors (georeferencing included) and errors after a free similarity alignment."""
    from services.colmap_model import read_model
    from services.pos import LocalFrame

    from .georef import estimate

    out_dir, scene_dir = Path(out_dir), Path(scene_dir)
    frame = LocalFrame(
        **{k: json.loads((out_dir / "georef.json").read_text())["frame"][k] for k in ("lat0", "lon0", "h0")}
    )
    truth = LocalFrame(**json.loads((scene_dir / "gt" / "scene.json").read_text())["origin"])
    _, est = read_model(out_dir / "sparse")
    _, gt = read_model(scene_dir / "gt" / "sparse")
    names = sorted(n for n in est if n in gt and n.split("/", 1)[0] == image_set)
    if not names:
        return {"num_images": 0}
    c_est = truth.from_wgs84(*frame.to_wgs84(np.array([est[n].center for n in names])))
    c_gt = np.array([gt[n].center for n in names])
    abs_err = np.linalg.norm(c_est - c_gt, axis=1)
    out = {"num_images": len(names), "num_true": sum(n.split("/", 1)[0] == image_set for n in gt)}
    out["absolute_m"] = {
        "mean": float(abs_err.mean()),
        "median": float(np.median(abs_err)),
        "p90": float(np.percentile(abs_err, 90)),
        "max": float(abs_err.max()),
    }
    if len(names) >= 3:
        R_est = [est[n].R.T for n in names]
        R_gt = [gt[n].R.T for n in names]
        geo = estimate(names, c_est, c_gt, 0.05, R_est, R_gt, conf={"min_max_error": 0.2})
        out["aligned_method"] = geo.method
        rel = np.array([np.linalg.norm(geo.residuals[n]) for n in names])
        out["aligned_m"] = {
            "mean": float(rel.mean()),
            "median": float(np.median(rel)),
            "p90": float(np.percentile(rel, 90)),
            "max": float(rel.max()),
        }
    return out
