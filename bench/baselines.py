"""Direct-matching baselines (SIFT, ALIKED+LightGlue) on a rendered synthetic survey.

    python bench/baselines.py [--preset isprs] [--seed 0] [--scene DIR] [--textures DIR] [--out DIR]

Renders the preset once (cached under runs/bench/scene-<preset>-seed<seed>), builds POS pairs, runs
both baselines on them with fresh feature caches (timings), evaluates the match files against the
ground truth and prints the tables. Timings are also given as ratios to SIFT measured in the same run,
which carry over between machines better than seconds.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from services.matching import direct  # noqa: E402
from services.matching import pairs as pairs_mod  # noqa: E402
from services.synth import SCENE_FILES, scene_complete  # noqa: E402
from shared.images import list_images  # noqa: E402
from shared.logging import setup_logging  # noqa: E402

logger = logging.getLogger("midview.bench")

DEFAULT_TEXTURES = ROOT.parent / "shared" / "data" / "lund_street"
METHODS = ("sift", "aliked-lightglue")
REFERENCE = "sift"


def ensure_scene(preset: str, seed: int, scene: Path, textures: Path | None) -> Path:
    """Render the preset into `scene` unless a complete scene is already there."""
    if scene_complete(scene):
        logger.info("reusing the rendered scene %s", scene)
        return scene
    from services import synth

    logger.info("rendering preset %s (seed %d, textures %s) into %s", preset, seed, textures, scene)
    t0 = time.perf_counter()
    synth.main(synth.confs[preset], scene, seed=seed, textures_dir=textures, overwrite=True)
    logger.info("rendered in %.0f s", time.perf_counter() - t0)
    return scene


def pos_pairs(scene: Path, out_dir: Path) -> tuple[list[tuple[str, str]], dict]:
    """POS pairs of the scene, with how many of the co-visible pairs they keep."""
    from services.evaluation import read_covisible

    names = list_images(scene / "images")
    aerial, ground = pairs_mod.split_sets(names)
    pairs = pairs_mod.get_pairs(pairs_mod.confs["pos"], names, scene / "pos.csv", scene / "cameras.json")
    pairs_mod.write_pairs(out_dir / "pairs-pos.txt", pairs)
    covisible = {(a, g) for a, g, _ in read_covisible(scene / "gt" / "covisible.csv", 0.05)}
    kept = covisible & set(pairs)
    info = {
        "aerial": len(aerial),
        "ground": len(ground),
        "all_pairs": len(aerial) * len(ground),
        "pos_pairs": len(pairs),
        "covisible_pairs": len(covisible),
        "covisible_kept": len(kept),
    }
    return pairs, info


def run_method(method: str, scene: Path, pairs: list, out_dir: Path, reuse_features: bool) -> dict:
    """Match with fresh features (unless reused); return timings and the evaluation summary."""
    from services.evaluation import evaluate_matches

    cache = out_dir / "features"
    fconf = direct.feature_conf(direct.confs[method])
    if not reuse_features:
        (cache / f"{fconf['output']}.h5").unlink(missing_ok=True)
    stats: dict = {}
    match_file = direct.main(direct.confs[method], scene, pairs, out_dir / f"{method}.h5", cache, stats=stats)
    summary = evaluate_matches(scene, match_file, out_dir / f"eval-{method}")
    return {"method": method, "stats": stats, "summary": summary}


def print_timings(results: list[dict], console) -> None:
    from rich.table import Table

    ref = next((r["stats"] for r in results if r["method"] == REFERENCE), None)
    table = Table(title=f"Timings (ratios: against {REFERENCE} in this run)")
    for col in (
        "method",
        "images",
        "extract s/img",
        "ratio",
        "pairs",
        "match s/pair",
        "ransac s/pair",
        "ratio",
    ):
        table.add_column(col, justify="left" if col == "method" else "right")
    for r in results:
        s = r["stats"]
        ext = s["extract_s"] / max(s["num_images"], 1)
        per_pair = (s["match_s"] + s["ransac_s"]) / max(s["num_pairs"], 1)
        row = [r["method"], str(s["num_images"]), f"{ext:.2f}", "-", str(s["num_pairs"])]
        row += [
            f"{s['match_s'] / max(s['num_pairs'], 1):.2f}",
            f"{s['ransac_s'] / max(s['num_pairs'], 1):.3f}",
            "-",
        ]
        if ref is not None:
            ref_ext = ref["extract_s"] / max(ref["num_images"], 1)
            ref_pair = (ref["match_s"] + ref["ransac_s"]) / max(ref["num_pairs"], 1)
            row[3] = f"{ext / ref_ext:.2f}" if ref_ext > 0 else "-"
            row[7] = f"{per_pair / ref_pair:.2f}" if ref_pair > 0 else "-"
        table.add_row(*row)
    console.print(table)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--preset", default="isprs", help="synthetic preset (small for continuity)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--scene", type=Path, help="a rendered scene folder (default: rendered and cached)")
    ap.add_argument("--textures", type=Path, help=f"facade photos (default: {DEFAULT_TEXTURES} if present)")
    ap.add_argument(
        "--out", type=Path, help="output folder (default: runs/bench/baselines-<preset>-seed<seed>)"
    )
    ap.add_argument(
        "--methods", default=",".join(METHODS), help="comma-separated subset of " + ", ".join(METHODS)
    )
    ap.add_argument(
        "--reuse-features", action="store_true", help="keep feature caches (no extraction timing)"
    )
    args = ap.parse_args(argv)
    setup_logging("INFO")
    from rich.console import Console

    from services.evaluation import print_summary_table

    console = Console(width=None if sys.stdout.isatty() else 120)
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    unknown = [m for m in methods if m not in direct.confs]
    if unknown:
        ap.error(f"unknown methods {unknown}: use {', '.join(direct.confs)}")
    textures = args.textures or (DEFAULT_TEXTURES if DEFAULT_TEXTURES.is_dir() else None)
    tag = f"{args.preset}-seed{args.seed}"
    scene = args.scene or ROOT / "runs" / "bench" / f"scene-{tag}"
    if args.scene is not None and not scene_complete(scene):
        ap.error(f"{scene} is not a complete scene folder (needs {', '.join(SCENE_FILES)})")
    out_dir = args.out or ROOT / "runs" / "bench" / f"baselines-{tag}"
    out_dir.mkdir(parents=True, exist_ok=True)

    ensure_scene(args.preset, args.seed, scene, textures)
    pairs, pinfo = pos_pairs(scene, out_dir)
    console.print(
        f"scene {scene}: {pinfo['aerial']} aerial, {pinfo['ground']} ground images; POS pairs "
        f"{pinfo['pos_pairs']} of {pinfo['all_pairs']}, keeping {pinfo['covisible_kept']} of "
        f"{pinfo['covisible_pairs']} co-visible pairs (overlap >= 0.05)"
    )
    results = [run_method(m, scene, pairs, out_dir, args.reuse_features) for m in methods]
    print_summary_table([r["summary"] for r in results], console=console)
    print_timings(results, console)
    report = {"scene": str(scene), "pairs": pinfo, "results": results}
    (out_dir / "baselines.json").write_text(json.dumps(report, indent=1, default=str))
    console.print(f"report: {out_dir / 'baselines.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
