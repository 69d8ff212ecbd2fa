"""Block-wise 3DGS refinement of a whole-scene model for the planned views (services.splat.blocks).

    python bench/splat_blocks.py --sparse JOB/sfm/sparse --images JOB/images --splat JOB/splat \
        --views JOB/plan/views.json --out runs/blocks [--workers 2] [--set train.steps=800 ...]

Plans the blocks, then trains them in `--workers` processes (each rasterizer single-threaded: one block
per core) and prints each block's crops, Gaussians, crop PSNR before and after and seconds. With
`--workers 1,2` it trains the same plan once per count (into OUT/w1, OUT/w2) and prints the speedup of
the fan-out. Render the result with bench/splat_views.py (`--splat blocks=OUT/w2`).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _train(args: tuple) -> dict:
    from services.splat.blocks import train_block
    from shared.logging import setup_logging

    setup_logging("INFO")
    return train_block(*args)


def train_all(plan: Path, ids: list[str], model: Path, sparse: Path, images: Path, out: Path, workers: int):
    """Train the blocks `ids` of `plan` into `out` with `workers` single-threaded processes."""
    import multiprocessing as mp

    out.mkdir(parents=True, exist_ok=True)
    (out / "plan.json").write_text(plan.read_text())
    env = {"NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
    old = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    try:
        t0 = time.perf_counter()
        with ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn")) as pool:
            docs = list(
                pool.map(_train, [(out / "plan.json", i, model, sparse, images, out, "cpu") for i in ids])
            )
        return {"seconds": time.perf_counter() - t0, "blocks": docs}
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def commit() -> str:
    import subprocess

    return subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=ROOT
    ).stdout.strip()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sparse", type=Path, required=True)
    ap.add_argument("--images", type=Path, required=True, help="the aerial images at the source resolution")
    ap.add_argument(
        "--splat", type=Path, required=True, help="the whole-scene 3DGS (training folder or .ply)"
    )
    ap.add_argument("--views", type=Path, required=True, help="a views.json of planned views")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--workers", default="2", help="comma-separated process counts (e.g. 1,2)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="blocks conf entry")
    ap.add_argument("--blocks", type=int, default=0, help="train only the first N blocks (0: all)")
    ap.add_argument("--json", type=Path, help="write the figures here")
    args = ap.parse_args()

    import pycolmap

    from services.conf import merge_conf, parse_overrides
    from services.splat import load_model
    from services.splat.blocks import confs, plan_blocks, write_plan
    from shared.logging import setup_logging

    setup_logging("INFO")
    conf = merge_conf(confs["default"], parse_overrides(args.set, confs["default"]))
    views = json.loads(args.views.read_text())["views"]
    t0 = time.perf_counter()
    plan = plan_blocks(conf, load_model(args.splat), pycolmap.Reconstruction(str(args.sparse)), views)
    plan["model"] = str(args.splat.resolve())
    plan_path = write_plan(plan, args.out / "plan.json")
    t_plan = time.perf_counter() - t0
    ids = [b["id"] for b in plan["blocks"]][: args.blocks or None]
    runs = {}
    for w in [int(x) for x in args.workers.split(",")]:
        runs[w] = train_all(plan_path, ids, args.splat, args.sparse, args.images, args.out / f"w{w}", w)
        print(f"{w} worker(s): {runs[w]['seconds']:.0f} s")
    first = runs[min(runs)]
    print(f"{len(ids)} blocks planned in {t_plan:.0f} s (gsd {plan['gsd_m']:.3f} m)")
    head = ("block", 6), ("views", 6), ("crops", 6), ("pixels", 9), ("G before", 10), ("G after", 9)
    head += ("PSNR before", 12), ("after", 7), ("s", 6)
    print("".join(f"{h:<{w}}" if h == "block" else f"{h:>{w}}" for h, w in head))
    for d in first["blocks"]:
        if not d["trained"]:
            print(f"{d['id']:<6}{len(d['views']):>6}  not trained: {d['reason']}")
            continue
        print(
            f"{d['id']:<6}{len(d['views']):>6}{d['crops']:>6}{d['pixels']:>9}{d['gaussians_before']:>10}"
            f"{d['gaussians']:>9}{d['psnr_before']:>12.2f}{d['psnr_after']:>7.2f}{d['seconds']:>6.0f}"
        )
    doc = {
        "command": "python " + " ".join(sys.argv),
        "commit": commit(),
        "plan_seconds": t_plan,
        "runs": {str(k): v for k, v in runs.items()},
    }
    if len(runs) > 1:
        lo, hi = min(runs), max(runs)
        doc["figures"] = {
            "blocks": len(ids),
            "steps_per_block": int(conf["train"]["steps"]),
            f"seconds_{lo}_worker": runs[lo]["seconds"],
            f"seconds_{hi}_workers": runs[hi]["seconds"],
            f"speedup_{hi}_workers": runs[lo]["seconds"] / runs[hi]["seconds"],
        }
        print(f"speedup {hi} workers against {lo}: {doc['figures'][f'speedup_{hi}_workers']:.2f}x")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(doc, indent=1))


if __name__ == "__main__":
    main()
