"""A reconstruction against the truth: registered images, 3D points, and camera pose errors after a
robust similarity alignment of the registered camera centres to the true ones."""

from __future__ import annotations

import csv
import json
import logging
from pathlib import Path

import numpy as np
import pycolmap

from .common import EvaluationError, image_set, read_gt_model, require_scene

logger = logging.getLogger(__name__)

default_conf = {
    "align_max_error": 0.5,  # metres: inlier threshold of the Sim3 LO-RANSAC on camera centres
    "min_aligned": 3,  # registered images (with a true pose) needed for the alignment
    "sets": ("aerial", "ground"),
}


def _has_model(path: Path) -> bool:
    return any((path / f"images.{ext}").is_file() for ext in ("bin", "txt"))


def read_reconstruction(model_dir: Path) -> tuple[pycolmap.Reconstruction, Path]:
    """Read a COLMAP model; for a mapper output folder of numbered sub-models, the one with most images."""
    model_dir = Path(model_dir)
    if not model_dir.is_dir():
        raise EvaluationError(f"model folder {model_dir} does not exist")
    candidates = (
        [model_dir] if _has_model(model_dir) else sorted(p for p in model_dir.iterdir() if _has_model(p))
    )
    if not candidates:
        raise EvaluationError(f"{model_dir}: no COLMAP model (images.bin / images.txt) found")
    best = None
    for path in candidates:
        try:
            rec = pycolmap.Reconstruction(str(path))
        except Exception as e:
            raise EvaluationError(f"{path}: cannot read the COLMAP model ({e})") from e
        if best is None or rec.num_reg_images() > best[0].num_reg_images():
            best = (rec, path)
    assert best is not None
    return best


def _rotation_angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))


def align_centres(src: np.ndarray, tgt: np.ndarray, max_error: float) -> tuple[np.ndarray, int] | None:
    """Robust similarity tgt_from_src (3x4 [sR | t]) and its number of inliers; None if degenerate."""
    opts = pycolmap.RANSACOptions(max_error=max_error)
    opts.random_seed = 0
    res = pycolmap.estimate_sim3d_robust(np.asarray(src, float), np.asarray(tgt, float), opts)
    if res is not None:
        return np.asarray(res["tgt_from_src"].matrix()), int(res["num_inliers"])
    sim = pycolmap.estimate_sim3d(np.asarray(src, float), np.asarray(tgt, float))
    return (np.asarray(sim.matrix()), len(src)) if sim is not None else None


def _finite(v: float) -> float:
    return float(v) if np.isfinite(v) else 0.0


def _stats(values: list[float]) -> dict:
    if not values:
        return {"mean": None, "median": None, "max": None}
    a = np.asarray(values, float)
    return {"mean": float(a.mean()), "median": float(np.median(a)), "max": float(a.max())}


def evaluate_sfm(
    scene_dir: Path, model_dir: Path, out_dir: Path | None = None, conf: dict | None = None
) -> dict:
    """Evaluate a reconstruction (COLMAP model in model_dir) against gt/sparse of a scene folder.

    Reports NRI per set (registered images with a true pose / images in the truth), N3P, mean
    reprojection error and track length, and, after a robust Sim3 alignment of the registered camera
    centres to the true ones (>= conf["min_aligned"] images), mean/median/max position error (m) and
    rotation error (deg) per set and overall. Errors are None where there is nothing to measure. With
    out_dir writes summary.json and per_image.csv.
    """
    conf = {**default_conf, **(conf or {})}
    require_scene(Path(scene_dir), "gt/sparse")
    _, gt_poses = read_gt_model(Path(scene_dir))
    rec, model_path = read_reconstruction(Path(model_dir))

    est = {}
    for img in rec.images.values():
        if img.has_pose and img.name in gt_poses:
            m = np.asarray(img.cam_from_world().matrix())
            est[img.name] = (m[:, :3], -m[:, :3].T @ m[:, 3])
    names = sorted(est)

    alignment = None
    per_image: list[dict] = []
    if len(names) >= conf["min_aligned"]:
        src = np.array([est[n][1] for n in names])
        tgt = np.array([gt_poses[n].center for n in names])
        res = align_centres(src, tgt, conf["align_max_error"])
        if res is not None:
            M, n_inl = res
            scale = float(np.cbrt(np.linalg.det(M[:, :3])))
            R_s = M[:, :3] / scale
            alignment = {
                "scale": scale,
                "num_inliers": n_inl,
                "num_images": len(names),
                "tgt_from_src": M.tolist(),
            }
            for n, c_tgt in zip(names, tgt, strict=True):
                R_est, c_est = est[n]
                c_al = M[:, :3] @ c_est + M[:, 3]
                R_al = R_est @ R_s.T  # cam_from_world in the true frame
                per_image.append(
                    {
                        "name": n,
                        "set": image_set(n),
                        "position_error": float(np.linalg.norm(c_al - c_tgt)),
                        "rotation_error": _rotation_angle_deg(gt_poses[n].R @ R_al.T),
                    }
                )

    sets = list(dict.fromkeys([*conf["sets"], *sorted({image_set(n) for n in gt_poses})]))
    per_set = {}
    for s in [*sets, "all"]:
        in_set = lambda n, s=s: s == "all" or image_set(n) == s  # noqa: E731
        rows = [r for r in per_image if in_set(r["name"])]
        per_set[s] = {
            "num_gt": sum(in_set(n) for n in gt_poses),
            "num_registered": sum(in_set(n) for n in names),
            "position_error": _stats([r["position_error"] for r in rows]),
            "rotation_error": _stats([r["rotation_error"] for r in rows]),
        }
    summary = {
        "scene": str(scene_dir),
        "model": str(model_path),
        "num_images_model": rec.num_images(),
        "num_registered_model": rec.num_reg_images(),
        "num_points3D": rec.num_points3D(),
        "mean_reprojection_error": _finite(rec.compute_mean_reprojection_error()),
        "mean_track_length": _finite(rec.compute_mean_track_length()),
        "alignment": alignment,
        "per_set": per_set,
        "conf": {**conf, "sets": list(conf["sets"])},
    }
    logger.info(
        "%s: %d/%d images registered, %d points, alignment %s",
        model_path,
        per_set["all"]["num_registered"],
        per_set["all"]["num_gt"],
        summary["num_points3D"],
        "ok" if alignment else "none",
    )
    if out_dir is not None:
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "summary.json").write_text(json.dumps(summary, indent=1))
        with open(out_dir / "per_image.csv", "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=("name", "set", "position_error", "rotation_error"))
            w.writeheader()
            w.writerows(per_image)
    return summary


def print_sfm_table(
    summary: dict, title: str = "Reconstruction vs. ground truth (pos: m, rot: deg)", console=None
) -> None:
    """A rich table with one row per set (and 'all') of an `evaluate_sfm` summary."""
    from rich.console import Console
    from rich.table import Table

    def fmt(v: float | None, digits: int) -> str:
        return "-" if v is None else f"{v:.{digits}f}"

    al = summary["alignment"]
    caption = (
        f"N3P {summary['num_points3D']}, reprojection error {summary['mean_reprojection_error']:.2f} px, "
        f"track length {summary['mean_track_length']:.2f}, "
        + (
            f"Sim3 scale {al['scale']:.3g}, {al['num_inliers']}/{al['num_images']} inliers"
            if al
            else "no alignment"
        )
    )
    table = Table(title=title, caption=caption)
    for col in ("set", "NRI", "pos mean", "pos med", "pos max", "rot mean", "rot med", "rot max"):
        table.add_column(col, justify="left" if col == "set" else "right")
    for s, r in summary["per_set"].items():
        pe, re = r["position_error"], r["rotation_error"]
        table.add_row(
            s,
            f"{r['num_registered']}/{r['num_gt']}",
            *(fmt(pe[k], 3) for k in ("mean", "median", "max")),
            *(fmt(re[k], 3) for k in ("mean", "median", "max")),
        )
    (console or Console()).print(table)


def main(conf: dict, scene_dir: Path, model_dir: Path, out_dir: Path) -> Path:
    """hloc-style entry: evaluate, write the outputs to out_dir and return the summary.json path."""
    evaluate_sfm(scene_dir, model_dir, out_dir, conf)
    return Path(out_dir) / "summary.json"
