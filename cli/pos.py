"""`midview pos`: check POS files against image folders."""

from __future__ import annotations

from pathlib import Path

import typer

app = typer.Typer(help="POS (position and orientation) files.", no_args_is_help=True)


@app.command("check")
def check(
    pos_file: Path = typer.Argument(..., help="POS CSV (docs/formats.md)"),
    images: Path = typer.Option(None, help="images/ folder whose aerial/ and ground/ files need POS"),
) -> None:
    """Validate a POS CSV (and, with --images, that POS and images name the same files)."""
    from services.pos import PosError, check_against_images, read_pos_csv
    from shared.images import list_images

    try:
        records = read_pos_csv(pos_file)
        if images is not None:
            check_against_images(records, list_images(images))
    except PosError as e:
        typer.secho(str(e), fg="red", err=True)
        raise typer.Exit(2) from None
    n_att = sum(r.R_world_from_cam is not None for r in records)
    typer.echo(f"{pos_file}: {len(records)} records, {n_att} with attitude: OK")
