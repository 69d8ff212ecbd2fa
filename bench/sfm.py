"""Aerial SfM benchmark: stage times and key figures on brighton_beach and the synthetic `small` preset.

    python bench/sfm.py                      # both datasets, work folder runs/bench-sfm
    python bench/sfm.py --only brighton --conf sift-fast

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

BRIGHTON = Path(__file__).resolve().parents[2] / "shared" / "data" / "brighton_beach" / "images"


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
    only: str = typer.Option(None, help="brighton or small"),
    scene: Path = typer.Option(None, help="an already rendered `small` scene folder (default: render one)"),
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
    (work / f"bench-{conf}.json").write_text(
        json.dumps({"reference_s": ref, "rows": rows}, indent=1, default=str)
    )


if __name__ == "__main__":
    typer.run(bench)
