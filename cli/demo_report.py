"""The demo's figures: the table of midview and the direct baselines against the ground truth (printed
and in report.html), and drawings of their matches on a few pairs."""

from __future__ import annotations

import json
from pathlib import Path


def nri_ground(sfm_eval: dict | None) -> str:
    if not sfm_eval:
        return "-"
    g = sfm_eval["per_set"].get("ground", {})
    return f"{g.get('num_registered', 0)}/{g.get('num_gt', 0)}"


def ground_error(sfm_eval: dict | None, key: str = "absolute_error") -> str:
    """Median / max of the ground cameras' position error (`key` of evaluate_sfm's per-set errors)."""
    if not sfm_eval:
        return "-"
    pe = sfm_eval["per_set"].get("ground", {}).get(key, {})
    return "-" if pe.get("median") is None else f"{pe['median']:.2f} / {pe['max']:.2f}"


def ground_within(sfm_eval: dict | None, metres: float = 0.5) -> int:
    """Ground images registered within `metres` of the truth in absolute terms (the georeferenced frame)."""
    if not sfm_eval or not sfm_eval.get("georef"):
        return 0
    rows = sfm_eval.get("per_image") or []
    return sum(r["set"] == "ground" and r.get("absolute_error", float("inf")) <= metres for r in rows)


def print_table(rows: list[dict], sfm_evals: dict[str, dict], console) -> None:
    from rich.table import Table

    table = Table(title="Aerial-ground matching on the co-visible pairs (means per pair)")
    cols = (
        "method",
        "NIM",
        "NCM",
        "GT-correct",
        "precision",
        "pooled prec.",
        "NMP",
        "NRI ground",
        "within 0.5 m",
        "abs err med / max (m)",
        "aerial-aligned (m)",
    )
    for col in cols:
        table.add_column(col, justify="left" if col == "method" else "right")
    for s in rows:
        table.add_row(*row_cells(s, sfm_evals.get(s["method"])))
    console.print(table)
    console.print(
        "NRI ground: ground images registered by the combined reconstruction with each method's matches "
        "(the same procedure); within 0.5 m and abs err: their camera centres' distance to the truth in "
        "the georeferenced frame (what a user gets); aerial-aligned: after aligning the model to the "
        "truth by its aerial cameras alone."
    )


def draw_pair(
    scene: Path, match_file: Path, aerial: str, ground: str, out_path: Path, max_lines: int = 120
) -> Path | None:
    """A side-by-side drawing of the verified matches of one pair (green: GT-correct, red: wrong)."""
    import cv2
    import numpy as np

    from services.evaluation import gt_correct_mask
    from services.evaluation.common import DepthMaps, read_gt_model
    from shared.matchfile import MatchFile

    with MatchFile(match_file) as mf:
        pm = mf.get_pair(aerial, ground)
        if pm is None:
            return None
        inl = np.ones(len(pm.matches), bool) if pm.inliers is None else np.asarray(pm.inliers, bool)
        m = pm.matches[inl]
        ka, kg = mf.keypoints(aerial)[m[:, 0]], mf.keypoints(ground)[m[:, 1]]
    cams, poses = read_gt_model(scene)
    with DepthMaps(scene / "gt" / "depth.h5") as d:
        ok = gt_correct_mask(
            ka, kg, cams[aerial], poses[aerial], d[aerial], cams[ground], poses[ground], d[ground]
        )
    ia = cv2.imread(str(scene / "images" / aerial))
    ig = cv2.imread(str(scene / "images" / ground))
    s = ig.shape[0] / ia.shape[0]
    ia = cv2.resize(ia, (round(ia.shape[1] * s), ig.shape[0]))
    canvas = np.concatenate([ia, ig], 1)
    order = np.random.default_rng(0).permutation(len(ka))[:max_lines]
    for i in order:
        p = (int(ka[i, 0] * s), int(ka[i, 1] * s))
        q = (int(kg[i, 0] + ia.shape[1]), int(kg[i, 1]))
        cv2.line(canvas, p, q, (0, 200, 0) if ok[i] else (0, 0, 255), 1, cv2.LINE_AA)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out_path), canvas, [cv2.IMWRITE_JPEG_QUALITY, 85])
    return out_path


def row_cells(s: dict, ev: dict | None) -> list[str]:
    """A method's cells of the demo's table: its match summary (evaluate_matches) and the combined
    reconstruction's ground figures (evaluate_sfm, or None)."""
    return [
        s["method"],
        f"{s['mean_nim']:.1f}",
        f"{s['mean_ncm']:.1f}",
        f"{s['mean_gt_correct']:.1f}",
        f"{s['mean_precision']:.3f}",
        f"{s['pooled_precision']:.3f}",
        f"{s['nmp']}/{s['num_pairs']}",
        nri_ground(ev),
        str(ground_within(ev)) if ev else "-",
        ground_error(ev),
        ground_error(ev, "aerial_aligned_error"),
    ]


def write_report_html(
    out: Path, scene: Path, files: dict, rows: list[dict], sfm_evals: dict[str, dict], timings: dict, job
) -> Path:
    """report.html: the dashboard's page of the job, static and self-contained (cli/report_page.py), with
    the table of every method against the ground truth and match drawings of a few pairs per method."""
    import csv

    from cli.report_page import jpeg_data_url, write_report_page

    # the pairs where midview has most GT-correct matches, drawn for every method
    per_pair = out / "eval" / Path(files["midview"]).stem / "per_pair.csv"
    picks: list[tuple[str, str]] = []
    if per_pair.is_file():
        with open(per_pair) as f:
            rs = sorted(csv.DictReader(f), key=lambda r: -int(r["gt_correct"]))
        picks = [(r["aerial"], r["ground"]) for r in rs[:3]]
    pictures = []
    for a, g in picks:
        for label, path in files.items():
            name = f"{Path(path).stem}__{Path(a).stem}_{Path(g).stem}.jpg"
            p = draw_pair(scene, Path(path), a, g, out / "pictures" / name)
            if p is not None:
                caption = f"{label}: {a} / {g} (green: correct under ground truth, red: wrong)"
                pictures.append({"caption": caption, "src": jpeg_data_url(p, 1400)})
    columns = [
        "method",
        "NIM",
        "NCM",
        "GT-correct",
        "precision",
        "pooled precision",
        "NMP",
        "NRI ground",
        "within 0.5 m",
        "ground abs error med / max (m)",
        "aerial-aligned (m)",
    ]
    table = [row_cells(s, sfm_evals.get(s["method"])) for s in rows]
    notes = [
        f"Synthetic survey {scene}: co-visible aerial-ground pairs of the ground truth, means per pair. "
        "GT-correct: verified matches within 3 px in both images through the true depth; NMP: pairs with "
        "at least 15 GT-correct matches; ground errors in the georeferenced frame (absolute), and after "
        "aligning the aerial cameras to the truth."
    ]
    ev = sfm_evals.get("midview")
    if ev:
        notes.append(
            f"midview's combined SfM: NRI aerial {ev['per_set']['aerial']['num_registered']}/"
            f"{ev['per_set']['aerial']['num_gt']}, ground {nri_ground(ev)}, N3P {ev['num_points3D']}."
        )
    notes.append("Timings (s): " + json.dumps({k: round(v, 1) for k, v in timings.items()}))
    evaluation = {
        "title": "midview and the direct baselines against the ground truth",
        "columns": columns,
        "rows": table,
        "notes": notes,
        "pictures": pictures,
    }
    path = write_report_page(out / "report.html", job, scene, evaluation)
    (out / "report.json").write_text(
        json.dumps({"rows": rows, "sfm": sfm_evals, "timings": timings}, indent=1, default=str)
    )
    return path
