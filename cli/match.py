"""`midview match`: aerial-ground matching and export of the matches to COLMAP."""

from __future__ import annotations

from pathlib import Path

import typer

app = typer.Typer(help="Match aerial and ground images; export matches to COLMAP.", no_args_is_help=True)

METHODS = ("sift", "aliked-lightglue")
PAIRS = ("all", "pos")


def _fail(message: str) -> None:
    typer.secho(message, fg="red", err=True)
    raise typer.Exit(2)


@app.command("direct")
def direct(
    scene: Path = typer.Argument(
        ..., help="scene folder (images/, pos.csv, cameras.json), e.g. from `midview synth`"
    ),
    method: str = typer.Option("aliked-lightglue", help=f"matcher: {' | '.join(METHODS)}"),
    pairs: str = typer.Option("pos", help=f"candidate pairs: {' | '.join(PAIRS)}"),
    out: Path = typer.Option(..., help="match file to write (HDF5, docs/formats.md)"),
    images: Path = typer.Option(None, help="images folder (default: SCENE/images)"),
    pos: Path = typer.Option(None, help="POS CSV (default: SCENE/pos.csv)"),
    cameras: Path = typer.Option(None, help="cameras.json (default: SCENE/cameras.json)"),
    cache: Path = typer.Option(None, help="feature cache folder (default: the folder of --out)"),
) -> None:
    """Match every candidate aerial-ground pair directly (local features + F-RANSAC)."""
    if method not in METHODS:
        _fail(f"unknown method {method!r}: use one of {', '.join(METHODS)}")
    if pairs not in PAIRS:
        _fail(f"unknown pairs {pairs!r}: use one of {', '.join(PAIRS)}")
    images = images or scene / "images"
    if not images.is_dir():
        _fail(f"image folder {images} does not exist")
    pos = pos or scene / "pos.csv"
    cameras = cameras or scene / "cameras.json"
    if pairs == "pos":
        for what, path in (("POS file", pos), ("cameras file", cameras)):
            if not path.is_file():
                _fail(f"{what} {path} does not exist (needed by --pairs pos)")

    from services.matching import direct as direct_mod
    from services.matching import pairs as pairs_mod
    from services.pos import PosError
    from shared.images import ImageError, list_images

    try:
        names = list_images(images)
        aerial, ground = pairs_mod.split_sets(names)
        if not aerial or not ground:
            _fail(
                f"{images} needs images in both aerial/ and ground/ ({len(aerial)} and {len(ground)} found)"
            )
        pair_list = pairs_mod.get_pairs(pairs_mod.confs[pairs], names, pos, cameras)
        pairs_mod.write_pairs(out.with_suffix(".pairs.txt"), pair_list)
        direct_mod.main(direct_mod.confs[method], images, pair_list, out, cache)
    except (PosError, ImageError, ValueError) as e:
        _fail(str(e))
    typer.echo(f"{len(pair_list)} pairs matched with {method} -> {out}")


@app.command("export")
def export(
    matches: Path = typer.Argument(..., help="match file (HDF5)"),
    database: Path = typer.Argument(..., help="COLMAP database to write"),
    cameras: Path = typer.Option(..., help="cameras.json with the intrinsics of each image set"),
    only_inliers: bool = typer.Option(False, help="export only the matches the RANSAC kept"),
) -> None:
    """Write the keypoints and verified matches of a match file into a COLMAP database."""
    for what, path in (("match file", matches), ("cameras file", cameras)):
        if not path.is_file():
            _fail(f"{what} {path} does not exist")

    from services.colmap_db import export_to_database
    from services.colmap_model import read_cameras_json

    try:
        export_to_database(matches, database, read_cameras_json(cameras), only_inliers=only_inliers)
    except (ValueError, KeyError, TypeError) as e:
        _fail(str(e))
    typer.echo(f"{matches} -> {database}")
