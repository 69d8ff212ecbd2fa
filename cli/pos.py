"""`midview pos`: check POS files against image folders."""

from __future__ import annotations

from pathlib import Path

import typer

app = typer.Typer(help="POS (position and orientation) files.", no_args_is_help=True)

FORMATS = {"csv": "POS CSV", "json": "POS JSON", "geo": "ODM geo.txt", "exif": "image EXIF/XMP"}


@app.command("check")
def check(
    pos_file: Path = typer.Argument(
        ...,
        help="POS: CSV (docs/formats.md), JSON, ODM geo.txt, or a folder of images (their EXIF/XMP)",
    ),
    images: Path = typer.Option(
        None, help="images/ folder (aerial/, ground/ inside) or a flat folder of aerial images"
    ),
    pitch_zero: str = typer.Option(
        "auto", "--pitch-zero", help="geo.txt angles: auto, nadir (ODM's) or horizon (DJI gimbal)"
    ),
    altitude: str = typer.Option("gps", "--altitude", help="EXIF heights: gps or relative (XMP)"),
) -> None:
    """Validate a POS file in any format midview reads (and, with --images, that POS and images name
    the same files; bare geo.txt names are matched to the images')."""
    from services.pos import PosError, image_paths, read_pos, sniff_format
    from shared.images import ImageError

    try:
        names = list(image_paths(images)) if images is not None else None
        records = read_pos(pos_file, image_names=names, pitch_zero=pitch_zero, altitude=altitude)
    except (PosError, ImageError, ValueError) as e:
        typer.secho(str(e), fg="red", err=True)
        raise typer.Exit(2) from None
    n_att = sum(r.R_world_from_cam is not None for r in records)
    crs = next((r.crs for r in records if r.crs), "EPSG:4979")
    kind = FORMATS[sniff_format(pos_file)]
    typer.echo(f"{pos_file}: {kind}, CRS {crs}, {len(records)} records, {n_att} with attitude: OK")
