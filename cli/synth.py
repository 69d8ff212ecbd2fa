"""`midview synth`: render a synthetic aerial + ground survey with exact ground truth."""

from __future__ import annotations

from pathlib import Path

import typer


def synth(
    out: Path = typer.Argument(..., help="output scene folder (docs/formats.md, 'Synthetic scene folder')"),
    preset: str = typer.Option(
        "small",
        help="tiny (tests, seconds), small (a block, minutes), small-walk (small with 40 ground images in"
        " sequence, 4 m apart), isprs (a 5-head oblique flight and facades with depth, real brick and"
        " transient cars, as hard as real surveys), isprs-flat (isprs with flat facades) or city",
    ),
    overrides: list[str] = typer.Option(
        [],
        "--set",
        help="KEY=VALUE entry of the preset (dotted, repeatable): --set scene.wall_photos=0",
    ),
    seed: int = typer.Option(0, help="random seed: same preset and seed give identical files"),
    textures: Path | None = typer.Option(
        None,
        "--textures",
        help="folder of facade photos (jpg/png, or an images/ subfolder); default procedural",
    ),
    supersample: int | None = typer.Option(None, help="samples per pixel side (default: the preset's)"),
    force: bool = typer.Option(False, "--force", help="replace the outputs of an existing scene in OUT"),
) -> None:
    """Render a synthetic urban survey: oblique UAV (aerial) and street-level (ground) images, a noisy POS
    file, camera intrinsics and the ground truth (true poses, depth maps, co-visible pairs, 3D points)."""
    from services.synth import confs

    if preset not in confs:
        typer.secho(f"unknown preset {preset!r}; choose one of {', '.join(confs)}", fg="red", err=True)
        raise typer.Exit(2)
    from services.conf import merge_conf, parse_overrides

    try:
        conf = merge_conf(confs[preset], parse_overrides(overrides, confs[preset]))
    except ValueError as e:
        typer.secho(f"--set: {e}", fg="red", err=True)
        raise typer.Exit(2) from None
    if textures is not None and not textures.is_dir():
        typer.secho(f"texture folder {textures} does not exist", fg="red", err=True)
        raise typer.Exit(2)
    if textures is not None:
        from services.synth.imaging import list_photos

        if not list_photos(textures):
            typer.secho(f"texture folder {textures} holds no jpg/png photos", fg="red", err=True)
            raise typer.Exit(2)
    if supersample is not None and not 1 <= supersample <= 8:
        typer.secho(f"--supersample must be between 1 and 8, not {supersample}", fg="red", err=True)
        raise typer.Exit(2)
    if out.exists() and not out.is_dir():
        typer.secho(f"{out} exists and is not a folder", fg="red", err=True)
        raise typer.Exit(2)
    if out.is_dir() and any(out.iterdir()) and not force:
        typer.secho(f"{out} is not empty; use --force to replace its scene", fg="red", err=True)
        raise typer.Exit(2)

    from services.synth import main, read_covisible

    main(conf, out, seed=seed, textures_dir=textures, supersample=supersample, overwrite=force)
    n_images = sum(1 for s in ("aerial", "ground") for _ in (out / "images" / s).glob("*.jpg"))
    typer.echo(f"{out}: {n_images} images, {len(read_covisible(out))} co-visible aerial-ground pairs")
