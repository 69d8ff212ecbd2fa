"""Aerial SfM benchmark: stage times and key figures on brighton_beach, caliterra and the synthetic
`small` preset, and the georeference of each: its method, uncertainty and how level the flight stands.

    python bench/sfm.py                      # every dataset, work folder runs/bench-sfm
    python bench/sfm.py --only brighton --conf sift-fast
    python bench/sfm.py --only caliterra --json docs/results/sfm-caliterra.json

caliterra (75 nadir images, consumer GPS in EXIF, no attitude) is flown at one height: the tilt of its
georeferenced flight plane against the vertical is the figure (`tilt_deg`), with the same model
georeferenced on the camera centres alone beside it.

Absolute times depend on the machine; the ratios are measured in the same run and compare better
across machines: matching and mapping time per image relative to the feature time per image, and the
feature time per image relative to a reference (one pycolmap SIFT extraction of a fixed 1600x1200
synthetic image, timed at the start of the run).
"""

from __future__ import annotations

import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import typer

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
BRIGHTON = DATA / "brighton_beach" / "images"
CALITERRA = DATA / "caliterra" / "images"


def reference_seconds() -> float:
    """Seconds of one pycolmap SIFT extraction of a fixed 1600x1200 textured image (best of 2)."""
    import pycolmap

    rng = np.random.default_rng(0)
    img = (rng.random((150, 200)) * 255).astype(np.float32)
    img = np.kron(img, np.ones((8, 8), np.float32)) / 255.0  # blocky texture: many blob responses
    opts = pycolmap.FeatureExtractionOptions()
    opts.sift.max_num_features = 8192
    sift = pycolmap.FeatureExtractor.create(opts, pycolmap.Device.cpu)
    best = np.inf
    for _ in range(2):
        t0 = time.perf_counter()
        sift.extract_from_float32_array(img)
        best = min(best, time.perf_counter() - t0)
    return float(best)


def run_one(name: str, conf: dict, image_dir: Path, out: Path, pos=None, cameras=None, scene=None) -> dict:
    from services.sfm import main
    from services.sfm.report import compare_with_truth

    t0 = time.perf_counter()
    main(conf, image_dir, out, pos, cameras)
    wall = time.perf_counter() - t0
    rep = json.loads((out / "report.json").read_text())
    row = {"dataset": name, "wall_s": wall, **rep["timings_s"], "report": rep}
    if scene is not None:
        row["truth"] = compare_with_truth(out, scene)
    return row


def georef_both_ways(out: Path) -> dict:
    """The georeference of an SfM output's model refitted on the camera centres alone and jointly (the
    default), from the images' EXIF POS: each one's flight-plane tilt, optical axes and uncertainty."""
    import pycolmap

    from services.pos import LocalFrame
    from services.sfm.aerial import read_pos_exif, select_records
    from services.sfm.georef import estimate

    doc = json.loads((out / "georef.json").read_text())
    frame = LocalFrame(*(doc["frame"][k] for k in ("lat0", "lon0", "h0")))
    rec = pycolmap.Reconstruction(str(out / "sparse"))
    imgs = sorted(rec.images.values(), key=lambda i: i.name)
    names = [i.name for i in imgs]
    pos = select_records(read_pos_exif(out / "images", names), names)
    src = np.array([i.projection_center() for i in imgs])
    R_rec = [i.cam_from_world().rotation.matrix().T for i in imgs]
    tgt = np.array([frame.from_wgs84(pos[n].lat, pos[n].lon, pos[n].h)[0] for n in names])
    sigma = 3.0
    fits = {
        "centres_only": estimate(names, src, tgt, sigma, R_rec, None, conf={"joint": False}),
        "joint": estimate(names, src, tgt, sigma, R_rec, None, pos_std=np.full((len(names), 3), np.nan)),
    }
    res = {}
    for k, g in fits.items():
        r = np.array([g.residuals[n] for n in names])
        res[k] = {
            "method": g.method,
            "tilt_deg": g.levels["flight_plane_tilt_deg"],
            "optical_axis_from_nadir_deg": g.levels["optical_axis_from_nadir_deg"],
            "off_plane_std_m": g.levels["off_plane_std_m"],
            "residual_median_m": {
                "horizontal": float(np.median(np.linalg.norm(r[:, :2], axis=1))),
                "vertical": float(np.median(np.abs(r[:, 2]))),
            },
            "pos_noise": g.noise or None,
            "uncertainty": g.uncertainty or None,
        }
    return res


def print_rows(rows: list[dict], ref: float) -> None:
    """Two tables: reconstruction figures, then stage times with their same-run ratios."""
    from rich.console import Console
    from rich.table import Table

    def table(title: str, cols: tuple[str, ...]) -> Table:
        t = Table(title=title)
        for c in cols:
            t.add_column(c, justify="left" if c == "dataset" else "right")
        return t

    figures = table(
        "aerial SfM: figures",
        (
            "dataset",
            "NRI",
            "N3P",
            "reproj px",
            "track",
            "georef mean/med/max m",
            "georef status",
            "att med deg",
            "abs err max m",
            "aligned err max m",
        ),
    )
    times = table(
        f"aerial SfM: stage times (reference: SIFT of one 1600x1200 image = {ref:.2f} s)",
        (
            "dataset",
            "features s",
            "matching s",
            "mapping s",
            "georef s",
            "total s",
            "feat s/img / ref",
            "match / feat",
            "map / feat",
        ),
    )
    for r in rows:
        rep = r["report"]
        g = rep["georef"]["residual_m"]
        att = rep["georef"]["attitude_deg"]["median"]
        truth = r.get("truth") or {}
        figures.add_row(
            r["dataset"],
            rep["NRI"],
            str(rep["num_points3D"]),
            f"{rep['mean_reprojection_error_px']:.2f}",
            f"{rep['mean_track_length']:.2f}",
            "-" if g["mean"] is None else f"{g['mean']:.2f}/{g['median']:.2f}/{g['max']:.2f}",
            rep["georef"].get("status", "-"),
            "-" if att is None else f"{att:.1f}",
            f"{truth['absolute_m']['max']:.2f}" if "absolute_m" in truth else "-",
            f"{truth['aligned_m']['max']:.3f}" if "aligned_m" in truth else "-",
        )
        times.add_row(
            r["dataset"],
            f"{r['features']:.1f}",
            f"{r['matching']:.1f}",
            f"{r['mapping']:.1f}",
            f"{r['georef']:.2f}",
            f"{r['total']:.1f}",
            f"{r['features'] / rep['num_images'] / ref:.2f}",
            f"{r['matching'] / r['features']:.2f}",
            f"{r['mapping'] / r['features']:.2f}",
        )
    console = Console()
    console.print(figures)
    console.print(times)
    for r in rows:
        for u in r["report"]["unregistered"]:
            print(f"  {r['dataset']}: not registered {u['name']}: {u['reason']}")


def bench(
    work: Path = typer.Option(Path("runs/bench-sfm"), help="work folder (synthetic scene cached here)"),
    conf: str = typer.Option("sift", help="services.sfm conf"),
    only: str = typer.Option(None, help="brighton, caliterra or small"),
    scene: Path = typer.Option(None, help="an already rendered `small` scene folder (default: render one)"),
    json_out: Path = typer.Option(None, "--json", help="also write the figures here (docs/results/...)"),
) -> None:
    """Run the aerial SfM on brighton_beach and the synthetic small preset; print times and figures."""
    from services.colmap_model import read_cameras_json
    from services.sfm import confs
    from shared.logging import setup_logging

    setup_logging("WARNING")
    work.mkdir(parents=True, exist_ok=True)
    ref = reference_seconds()
    rows = []
    if only in (None, "brighton"):
        if BRIGHTON.is_dir():
            rows.append(run_one("brighton_beach", confs[conf], BRIGHTON, work / f"brighton-{conf}"))
        else:
            print(f"skipping brighton_beach: {BRIGHTON} absent")
    if only in (None, "caliterra"):
        if CALITERRA.is_dir():
            out = work / f"caliterra-{conf}"
            rows.append(run_one("caliterra", confs[conf], CALITERRA, out))
            rows[-1]["georef_both_ways"] = georef_both_ways(out)
        else:
            print(f"skipping caliterra: {CALITERRA} absent")
    if only in (None, "small"):
        try:
            from services.synth import confs as synth_confs
            from services.synth import main as synth_main
        except ImportError:
            print("skipping the synthetic preset: services.synth is not available")
        else:
            scene = scene or work / "synth-small"
            if not (scene / "gt" / "sparse").is_dir():
                with tempfile.TemporaryDirectory(dir=work) as tmp:
                    synth_main(synth_confs["small"], Path(tmp) / "scene", seed=0)
                    (Path(tmp) / "scene").rename(scene)
            rows.append(
                run_one(
                    "synth small",
                    confs[conf],
                    scene / "images",
                    work / f"small-{conf}",
                    scene / "pos.csv",
                    read_cameras_json(scene / "cameras.json"),
                    scene,
                )
            )
    print_rows(rows, ref)
    for r in rows:
        if "georef_both_ways" in r:
            for k, g in r["georef_both_ways"].items():
                print(
                    f"  {r['dataset']} georeferenced {k.replace('_', ' ')}: flight plane "
                    f"{g['tilt_deg']:.2f} deg from the vertical, optical axes "
                    f"{g['optical_axis_from_nadir_deg']:.1f} deg from nadir "
                    f"(median), tilt std {((g['uncertainty'] or {}).get('tilt_deg') or float('nan')):.2f} deg"
                )
    (work / f"bench-{conf}.json").write_text(
        json.dumps({"reference_s": ref, "rows": rows}, indent=1, default=str)
    )
    if json_out:
        json_out.parent.mkdir(parents=True, exist_ok=True)
        json_out.write_text(json.dumps(results_doc(rows, ref, conf), indent=1, default=str))
        print(f"figures: {json_out}")


def results_doc(rows: list[dict], ref: float, conf: str) -> dict:
    """docs/results/sfm-*.json: the command, the commit, and per dataset the figures (caliterra's
    tilt_deg at the top when it ran)."""
    import subprocess

    commit = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()
    figures: dict = {}
    for r in rows:
        rep = r["report"]
        f = {
            "NRI": rep["NRI"],
            "num_points3D": rep["num_points3D"],
            "mean_reprojection_error_px": rep["mean_reprojection_error_px"],
            "georef_status": rep["georef"].get("status"),
            "georef_method": rep["georef"].get("method"),
            "georef_residual_m": rep["georef"]["residual_m"],
            "georef_uncertainty": rep["georef"].get("uncertainty"),
            "levels": rep["georef"].get("levels"),
            "seconds": r["wall_s"],
            "truth": r.get("truth"),
        }
        if "georef_both_ways" in r:
            f["georef_both_ways"] = r["georef_both_ways"]
            f["tilt_deg"] = (rep["georef"].get("levels") or {}).get("flight_plane_tilt_deg")
        figures[r["dataset"]] = f
    cal = figures.get("caliterra")
    return {
        "command": "python bench/sfm.py " + " ".join(sys.argv[1:]),
        "commit": commit,
        "conf": conf,
        "reference_s": ref,
        "figures": {**({"tilt_deg": cal["tilt_deg"]} if cal else {}), **figures},
    }


if __name__ == "__main__":
    typer.run(bench)
