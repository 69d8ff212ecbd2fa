"""A reconstruction against the truth: registered images, 3D points, and camera pose errors in absolute
terms (the model's georeferenced frame against the truth's), after aligning the aerial cameras alone,
and after a robust similarity alignment of all registered camera centres to the true ones."""

from __future__ import annotations

import csv
import json
import logging
from pathlib import Path

import numpy as np
import pycolmap

from services.geometry import pose_of_image, rotation_angle_deg
from services.pos import LocalFrame

from .common import EvaluationError, image_set, read_gt_model, require_scene

logger = logging.getLogger(__name__)

default_conf = {
    "align_max_error": 0.5,  # metres: inlier threshold of the Sim3 LO-RANSAC on camera centres
    "min_aligned": 3,  # registered images (with a true pose) needed for the alignment
    "sets": ("aerial", "ground"),
}
# per image and per set: absolute (georeferenced frame), after aligning the aerial cameras, after
# aligning all cameras (position, rotation)
ERROR_KEYS = (
    "absolute_error",
    "absolute_rotation_error",
    "aerial_aligned_error",
    "position_error",
    "rotation_error",
)


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
        return {"mean": None, "median": None, "p90": None, "max": None}
    a = np.asarray(values, float)
    return {
        "mean": float(a.mean()),
        "median": float(np.median(a)),
        "p90": float(np.percentile(a, 90)),
        "max": float(a.max()),
    }


def find_georef(model_dir: Path) -> Path | None:
    """The georef.json of a model: in its folder or the one or two above (JOB/sfm/sparse/0 -> JOB/sfm)."""
    for d in (model_dir, *list(model_dir.parents)[:2]):
        if (d / "georef.json").is_file():
            return d / "georef.json"
    return None


def read_frame(georef_path: Path | None) -> LocalFrame | None:
    """The local ENU frame of a georef.json (None without one, or when it holds no frame)."""
    if georef_path is None:
        return None
    try:
        f = json.loads(Path(georef_path).read_text())["frame"]
        return LocalFrame(float(f["lat0"]), float(f["lon0"]), float(f["h0"]))
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise EvaluationError(f"{georef_path}: no readable frame ({e})") from e


def to_truth_frame(frame: LocalFrame, truth: LocalFrame) -> tuple[np.ndarray, callable]:
    """(R, f): rotation and point map taking the model's ENU frame to the truth's (through WGS84)."""
    R = frame.rotation_to_enu_at(truth.lat0, truth.lon0)
    return R, lambda X: truth.from_wgs84(*frame.to_wgs84(np.atleast_2d(X)))


def _apply(M: np.ndarray, X: np.ndarray) -> np.ndarray:
    return np.atleast_2d(X) @ M[:, :3].T + M[:, 3]


def _alignment(src: np.ndarray, tgt: np.ndarray, conf: dict) -> tuple[np.ndarray, dict] | None:
    res = align_centres(src, tgt, conf["align_max_error"]) if len(src) >= conf["min_aligned"] else None
    if res is None:
        return None
    M, n_inl = res
    scale = float(np.cbrt(np.linalg.det(M[:, :3])))
    return M, {"scale": scale, "num_inliers": n_inl, "num_images": len(src), "tgt_from_src": M.tolist()}


def evaluate_sfm(
    scene_dir: Path,
    model_dir: Path,
    out_dir: Path | None = None,
    conf: dict | None = None,
    georef: Path | None = None,
) -> dict:
    """Evaluate a reconstruction (COLMAP model in model_dir) against gt/sparse of a scene folder.

    Reports NRI per set (registered images with a true pose / images in the truth), N3P, mean
    reprojection error and track length, and camera errors three ways, per set and overall (mean,
    median, p90, max):
    - `absolute_error` (m) and `absolute_rotation_error` (deg): in the model's georeferenced frame
      (`georef`, by default the georef.json beside the model) taken to the truth's through WGS84, with
      no alignment to the truth: what a user gets. None when the model has no georef.json or the scene
      no origin.
    - `aerial_aligned_error`: after a robust Sim3 alignment of the aerial cameras alone to the truth.
    - `position_error` and `rotation_error`: after a robust Sim3 alignment of all registered cameras
      (>= conf["min_aligned"]), the ground cameras included.
    Errors are None where there is nothing to measure. With out_dir writes summary.json and
    per_image.csv.
    """
    conf = {**default_conf, **(conf or {})}
    require_scene(Path(scene_dir), "gt/sparse")
    _, gt_poses = read_gt_model(Path(scene_dir))
    rec, model_path = read_reconstruction(Path(model_dir))
    georef = Path(georef) if georef is not None else find_georef(Path(model_path))
    frame = read_frame(georef)
    scene_json = Path(scene_dir) / "gt" / "scene.json"
    origin = json.loads(scene_json.read_text()).get("origin") if scene_json.is_file() else None
    truth = LocalFrame(**origin) if origin else None

    est = {}
    for img in rec.images.values():
        if img.has_pose and img.name in gt_poses:
            pose = pose_of_image(img)
            est[img.name] = (pose.R, pose.center)
    names = sorted(est)
    rows = {n: {"name": n, "set": image_set(n)} for n in names}
    _absolute_errors(rows, est, gt_poses, frame, truth)
    aerial_al, all_al = _aligned_errors(rows, est, gt_poses, conf)
    per_image = list(rows.values())
    per_set = _per_set(per_image, names, gt_poses, conf)
    summary = {
        "scene": str(scene_dir),
        "model": str(model_path),
        "georef": str(georef) if frame is not None else None,
        "num_images_model": rec.num_images(),
        "num_registered_model": rec.num_reg_images(),
        "num_points3D": rec.num_points3D(),
        "mean_reprojection_error": _finite(rec.compute_mean_reprojection_error()),
        "mean_track_length": _finite(rec.compute_mean_track_length()),
        "alignment": all_al[1] if all_al else None,
        "aerial_alignment": aerial_al[1] if aerial_al else None,
        "per_set": per_set,
        "per_image": per_image,
        "conf": {**conf, "sets": list(conf["sets"])},
    }
    logger.info(
        "%s: %d/%d images registered, %d points, georeferenced %s, alignment %s",
        model_path,
        per_set["all"]["num_registered"],
        per_set["all"]["num_gt"],
        summary["num_points3D"],
        "yes" if summary["georef"] else "no",
        "ok" if all_al else "none",
    )
    if out_dir is not None:
        _write(summary, Path(out_dir))
    return summary


def _absolute_errors(rows: dict, est: dict, gt_poses: dict, frame, truth) -> None:
    """Each row's absolute_error (m) and absolute_rotation_error (deg): the model's georeferenced frame
    taken to the truth's through WGS84, no alignment (nothing without a georef or a scene origin)."""
    names = sorted(est)
    if not names or frame is None or truth is None:
        return
    R_t, to_truth = to_truth_frame(frame, truth)
    centres = to_truth(np.array([est[n][1] for n in names]))
    for n, c in zip(names, centres, strict=True):
        rows[n]["absolute_error"] = float(np.linalg.norm(c - gt_poses[n].center))
        rows[n]["absolute_rotation_error"] = rotation_angle_deg(gt_poses[n].R @ (est[n][0] @ R_t.T).T)


def _aligned_errors(rows: dict, est: dict, gt_poses: dict, conf: dict) -> tuple:
    """Each row's aerial_aligned_error (a robust Sim3 of the aerial cameras to the truth), and its
    position_error and rotation_error after one of all the cameras: (aerial alignment, alignment),
    each (matrix, report) or None."""
    names = sorted(est)
    src = {n: est[n][1] for n in names}
    tgt = {n: gt_poses[n].center for n in names}
    aerial = [n for n in names if image_set(n) == "aerial"]
    aerial_al = _alignment(np.array([src[n] for n in aerial]), np.array([tgt[n] for n in aerial]), conf)
    if aerial_al is not None:
        for n in names:
            rows[n]["aerial_aligned_error"] = float(np.linalg.norm(_apply(aerial_al[0], src[n])[0] - tgt[n]))
    all_al = _alignment(np.array([src[n] for n in names]), np.array([tgt[n] for n in names]), conf)
    if all_al is not None:
        M = all_al[0]
        R_s = M[:, :3] / all_al[1]["scale"]
        for n in names:
            rows[n]["position_error"] = float(np.linalg.norm(_apply(M, src[n])[0] - tgt[n]))
            rows[n]["rotation_error"] = rotation_angle_deg(gt_poses[n].R @ (est[n][0] @ R_s.T).T)
    return aerial_al, all_al


def _per_set(per_image: list[dict], names: list[str], gt_poses: dict, conf: dict) -> dict:
    """Per set (and "all"): images in the truth, registered, and the statistics of each error."""
    sets = list(dict.fromkeys([*conf["sets"], *sorted({image_set(n) for n in gt_poses})]))
    per_set = {}
    for s in [*sets, "all"]:
        in_set = lambda n, s=s: s == "all" or image_set(n) == s  # noqa: E731
        rs = [r for r in per_image if in_set(r["name"])]
        per_set[s] = {
            "num_gt": sum(in_set(n) for n in gt_poses),
            "num_registered": sum(in_set(n) for n in names),
            **{k: _stats([r[k] for r in rs if k in r]) for k in ERROR_KEYS},
        }
    return per_set


def _write(summary: dict, out_dir: Path) -> None:
    """summary.json and per_image.csv."""
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=1))
    with open(out_dir / "per_image.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=("name", "set", *ERROR_KEYS))
        w.writeheader()
        w.writerows(summary["per_image"])


def print_sfm_table(
    summary: dict, title: str = "Reconstruction vs. ground truth (positions: m, rotations: deg)", console=None
) -> None:
    """A rich table with one row per set (and 'all') of an `evaluate_sfm` summary: absolute errors,
    errors after aligning the aerial cameras, and after aligning all cameras."""
    from rich.console import Console
    from rich.table import Table

    def fmt(v: float | None, digits: int) -> str:
        return "-" if v is None else f"{v:.{digits}f}"

    al, aal = summary["alignment"], summary.get("aerial_alignment")
    caption = "; ".join(
        [
            f"all-camera Sim3 scale {al['scale']:.4g}, {al['num_inliers']}/{al['num_images']} inliers"
            if al
            else "no alignment",
            "absolute: the georeferenced model" if summary.get("georef") else "not georeferenced",
            *([f"aerial alignment scale {aal['scale']:.4g}"] if aal else []),
            f"N3P {summary['num_points3D']}, reprojection error {summary['mean_reprojection_error']:.2f} px, "
            f"track length {summary['mean_track_length']:.2f}",
        ]
    )
    table = Table(title=title, caption=caption)
    cols = (
        "set",
        "NRI",
        "abs med",
        "abs p90",
        "abs max",
        "abs rot med",
        "aerial-aligned med",
        "max",
        "all-aligned med",
        "max",
        "rot med",
    )
    for col in cols:
        table.add_column(col, justify="left" if col == "set" else "right")
    for s, r in summary["per_set"].items():
        ab, aa, pe = r["absolute_error"], r["aerial_aligned_error"], r["position_error"]
        table.add_row(
            s,
            f"{r['num_registered']}/{r['num_gt']}",
            *(fmt(ab[k], 3) for k in ("median", "p90", "max")),
            fmt(r["absolute_rotation_error"]["median"], 3),
            *(fmt(aa[k], 3) for k in ("median", "max")),
            *(fmt(pe[k], 3) for k in ("median", "max")),
            fmt(r["rotation_error"]["median"], 3),
        )
    (console or Console()).print(table)


def main(conf: dict, scene_dir: Path, model_dir: Path, out_dir: Path) -> Path:
    """hloc-style entry: evaluate, write the outputs to out_dir and return the summary.json path."""
    evaluate_sfm(scene_dir, model_dir, out_dir, conf)
    return Path(out_dir) / "summary.json"
