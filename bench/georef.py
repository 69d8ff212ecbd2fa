"""Georeference benchmark: the rotation and scale error of the aerial georeference, before (a similarity
fitted to the camera centres alone) and after (the joint fit of centres, POS attitudes or an
orientation prior, each weighted by its noise), against the truth.

    python bench/georef.py                  # the synthetic small preset, work folder runs/bench-georef
    python bench/georef.py --preset small-walk --scene runs/small-walk --sfm runs/bench/.../base/sfm
    python bench/georef.py --json docs/results/georef-tilt.json

Two parts, both measured in the same run:
- the aerial SfM model of a synthetic preset (a flight at one altitude; real reconstruction, POS
  with the preset's noise): both georeferences of the same model, their rotation and scale errors;
- simulated flights at one altitude (40 images, the preset's POS noise, --trials of them): the median
  and 90th percentile of the rotation error of each method, and the same with no attitudes in the POS
  (the orientation prior instead).
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import typer

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def _angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))


def georef_errors(geo, src: np.ndarray, R_rec: list, frame, truth, gt_centres, gt_R) -> dict:
    """Rotation error (deg: the chordal mean of the true world-from-camera rotations against the
    georeferenced ones), tilt error (deg: the true vertical against the georeferenced one), scale error
    (relative) and absolute centre errors (m) of a georeference `geo` of centres `src`."""
    from services.evaluation.sfm import align_centres, to_truth_frame
    from services.sfm.georef import mean_rotation

    R_t, to_truth = to_truth_frame(frame, truth)
    R_geo = [R_t @ geo.R @ Rr for Rr in R_rec]
    D = mean_rotation([Rg @ Re.T for Rg, Re in zip(gt_R, R_geo, strict=True)])  # truth from georeferenced
    c = to_truth(geo.apply(src))
    M, _ = align_centres(c, gt_centres, 0.5)
    err = np.linalg.norm(c - gt_centres, axis=1)
    return {
        "rotation_error_deg": _angle_deg(D),
        "tilt_error_deg": float(np.degrees(np.arccos(np.clip((D @ [0, 0, 1])[2], -1, 1)))),
        "scale_error": float(np.cbrt(np.linalg.det(M[:, :3])) - 1.0),
        "abs_error_m": {"median": float(np.median(err)), "max": float(err.max())},
        "method": geo.method,
        "uncertainty": geo.uncertainty or None,
    }


def on_model(scene: Path, sfm_dir: Path) -> dict:
    """Both georeferences of one aerial SfM model of a synthetic scene."""
    from services.colmap_model import read_model
    from services.evaluation.sfm import read_frame
    from services.pos import LocalFrame, read_pos
    from services.sfm.georef import estimate

    truth = LocalFrame(**json.loads((scene / "gt" / "scene.json").read_text())["origin"])
    frame = read_frame(sfm_dir / "georef.json")
    _, est = read_model(sfm_dir / "sparse")
    _, gt = read_model(scene / "gt" / "sparse")
    records = {r.name: r for r in read_pos(scene / "pos.csv")}
    names = sorted(n for n in est if n in gt and n in records and n.startswith("aerial/"))
    src = np.array([est[n].center for n in names])
    R_rec = [est[n].R.T for n in names]
    tgt = np.array([frame.from_wgs84(records[n].lat, records[n].lon, records[n].h)[0] for n in names])
    R_pos = [
        frame.rotation_to_enu_at(records[n].lat, records[n].lon).T @ records[n].R_world_from_cam
        for n in names
    ]
    std = np.array([[records[n].std_xy, records[n].std_xy, records[n].std_z] for n in names], float)
    att = np.array([records[n].std_att for n in names], float)
    sigma = float(np.median(std[:, 0]))
    gt_c = np.array([gt[n].center for n in names])
    gt_R = [gt[n].R.T for n in names]
    before = estimate(names, src, tgt, sigma, R_rec, R_pos, conf={"joint": False})
    after = estimate(names, src, tgt, sigma, R_rec, R_pos, pos_std=std, att_std_deg=att)
    no_att = estimate(names, src, tgt, sigma, R_rec, None, pos_std=np.full_like(std, np.nan))
    return {
        "num_images": len(names),
        "before": georef_errors(before, src, R_rec, frame, truth, gt_c, gt_R),
        "after": georef_errors(after, src, R_rec, frame, truth, gt_c, gt_R),
        "after_without_attitudes": georef_errors(no_att, src, R_rec, frame, truth, gt_c, gt_R),
    }


def simulated(trials: int, n: int, noise: dict) -> dict:
    """Rotation errors of the georeference of simulated flights at one altitude (nadir, 3 degree camera
    tilts), the POS with `noise` (std_xy, std_z, std_att): centres only, joint with attitudes, joint with
    the orientation prior (no attitudes, no stated std)."""
    from scipy.spatial.transform import Rotation

    from services.pos.attitude import ypr_to_matrix
    from services.sfm.georef import estimate

    errs: dict[str, list[float]] = {"centres only": [], "joint, attitudes": [], "joint, prior": []}
    for seed in range(trials):
        rng = np.random.default_rng(seed)
        C = np.c_[rng.uniform(-40, 40, (n, 2)), 60 + rng.normal(0, 0.4, n)]
        tilt = Rotation.from_rotvec(rng.normal(0, np.radians(3), (n, 3)) * [1, 1, 0]).as_matrix()
        R_true = [ypr_to_matrix(rng.uniform(0, 360), -90, 0) @ T for T in tilt]
        Rg = Rotation.random(random_state=seed).as_matrix()
        s, t = 0.3, rng.normal(0, 5, 3)
        src = ((C - t) @ Rg) / s
        R_rec = [Rg.T @ R for R in R_true]
        std = np.array([noise["std_xy"], noise["std_xy"], noise["std_z"]])
        tgt = C + rng.normal(0, 1, (n, 3)) * std
        att = Rotation.from_rotvec(rng.normal(0, np.radians(noise["std_att"]), (n, 3))).as_matrix()
        R_pos = [R @ A for R, A in zip(R_true, att, strict=True)]
        names = [f"aerial/{i}.jpg" for i in range(n)]
        fits = {
            "centres only": estimate(names, src, tgt, noise["std_xy"], R_rec, R_pos, conf={"joint": False}),
            "joint, attitudes": estimate(
                names,
                src,
                tgt,
                noise["std_xy"],
                R_rec,
                R_pos,
                pos_std=np.tile(std, (n, 1)),
                att_std_deg=np.full(n, noise["std_att"]),
            ),  # fmt: skip
            "joint, prior": estimate(
                names, src, tgt, noise["std_xy"], R_rec, None, pos_std=np.full((n, 3), np.nan)
            ),
        }
        for k, g in fits.items():
            errs[k].append(_angle_deg(g.R.T @ Rg))
    return {
        k: {
            "median_deg": float(np.median(v)),
            "p90_deg": float(np.percentile(v, 90)),
            "max_deg": float(np.max(v)),
        }
        for k, v in errs.items()
    }


def _commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()
    except OSError:
        return ""


def bench(
    preset: str = typer.Option("small", help="synthetic preset (flown at one altitude)"),
    scene: Path = typer.Option(None, help="an already rendered scene folder (default: render one)"),
    work: Path = typer.Option(Path("runs/bench-georef"), help="work folder"),
    sfm: Path = typer.Option(None, help="an aerial SfM output of the scene to use (default: run one)"),
    trials: int = typer.Option(100, help="simulated flights"),
    json_out: Path = typer.Option(None, "--json", help="also write the figures here"),
) -> None:
    """Print the georeference's rotation and scale errors before and after the joint fit."""
    from rich.console import Console
    from rich.table import Table

    from services.colmap_model import read_cameras_json
    from services.sfm import confs as sfm_confs
    from services.sfm import main as sfm_main
    from services.synth import confs as synth_confs
    from services.synth import main as synth_main
    from shared.logging import setup_logging

    setup_logging("WARNING")
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    scene = scene or work / f"synth-{preset}"
    if not (scene / "gt" / "sparse").is_dir():
        synth_main(synth_confs[preset], scene, seed=0, overwrite=True)
    sfm_dir = sfm or work / f"sfm-{scene.name}"
    if not (sfm_dir / "georef.json").is_file():
        sfm_main(
            sfm_confs["sift"],
            scene / "images",
            sfm_dir,
            scene / "pos.csv",
            read_cameras_json(scene / "cameras.json"),
        )
    model = on_model(scene, sfm_dir)
    noise = synth_confs[preset]["pos"]["aerial"]
    sim = simulated(trials, 40, noise)
    console = Console()
    t = Table(title=f"aerial georeference of {preset} ({model['num_images']} images) against the truth")
    for c in (
        "georeference",
        "rotation err deg",
        "tilt err deg",
        "scale err",
        "abs err med m",
        "abs err max m",
    ):
        t.add_column(c, justify="left" if c == "georeference" else "right")
    for k in ("before", "after", "after_without_attitudes"):
        r = model[k]
        t.add_row(
            k.replace("_", " "),
            f"{r['rotation_error_deg']:.3f}",
            f"{r['tilt_error_deg']:.3f}",
            f"{r['scale_error']:+.4f}",
            f"{r['abs_error_m']['median']:.3f}",
            f"{r['abs_error_m']['max']:.3f}",
        )
    console.print(t)
    t2 = Table(title=f"{trials} simulated flights at one altitude, 40 images, POS noise {noise}")
    for c in ("georeference", "rotation err median deg", "p90", "max"):
        t2.add_column(c, justify="left" if c == "georeference" else "right")
    for k, r in sim.items():
        t2.add_row(k, f"{r['median_deg']:.3f}", f"{r['p90_deg']:.3f}", f"{r['max_deg']:.3f}")
    console.print(t2)
    doc = {
        "command": "python bench/georef.py " + " ".join(sys.argv[1:]),
        "commit": _commit(),
        "preset": preset,
        "figures": {
            "before": {
                k: model["before"][k]
                for k in ("rotation_error_deg", "tilt_error_deg", "scale_error", "abs_error_m")
            },
            "after": {
                k: model["after"][k]
                for k in ("rotation_error_deg", "tilt_error_deg", "scale_error", "abs_error_m")
            },
            "after_without_attitudes": {
                k: model["after_without_attitudes"][k]
                for k in ("rotation_error_deg", "tilt_error_deg", "scale_error", "abs_error_m")
            },
            "after_uncertainty": model["after"]["uncertainty"],
            "simulated_level_flights": {"trials": trials, "images": 40, "pos_noise": noise, **sim},
        },
        "seconds": time.perf_counter() - t0,
    }
    if json_out:
        json_out.parent.mkdir(parents=True, exist_ok=True)
        json_out.write_text(json.dumps(doc, indent=1))
        console.print(f"figures: {json_out}")


if __name__ == "__main__":
    typer.run(bench)
