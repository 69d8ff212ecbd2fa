"""`midview eval`: evaluate matches and reconstructions against the ground truth of a synthetic scene."""

from __future__ import annotations

from pathlib import Path

import typer

app = typer.Typer(help="Evaluate against the ground truth of a synthetic scene.", no_args_is_help=True)


def _fail(message: str) -> None:
    typer.secho(message, fg="red", err=True)
    raise typer.Exit(2)


@app.command("matches")
def matches(
    scene: Path = typer.Argument(
        ..., metavar="SCENE", help="synthetic scene folder (gt/ inside, docs/formats.md)"
    ),
    match_file: Path = typer.Argument(..., metavar="MATCHES", help="match file (matches.h5)"),
    out: Path = typer.Option(None, "--out", help="folder for per_pair.csv and summary.json"),
    gt_px: float = typer.Option(3.0, "--gt-px", help="max reprojection error of a correct match (px)"),
    min_overlap: float = typer.Option(0.05, "--min-overlap", help="min overlap of an evaluated pair"),
) -> None:
    """Match quality on the co-visible aerial-ground pairs: NIM, NCM, GT-correct, precision, NMP."""
    from services.evaluation import EvaluationError, evaluate_matches, print_summary_table

    try:
        summary = evaluate_matches(scene, match_file, out, {"gt_px": gt_px, "min_overlap": min_overlap})
    except EvaluationError as e:
        _fail(str(e))
    print_summary_table([summary])
    if out is not None:
        typer.echo(f"wrote {out / 'per_pair.csv'} and {out / 'summary.json'}")


@app.command("sfm")
def sfm(
    scene: Path = typer.Argument(..., metavar="SCENE", help="synthetic scene folder (gt/sparse inside)"),
    model: Path = typer.Argument(
        ..., metavar="MODEL", help="COLMAP model folder (or a mapper output of numbered models)"
    ),
    out: Path = typer.Option(None, "--out", help="folder for summary.json and per_image.csv"),
) -> None:
    """A reconstruction against the true poses: NRI, N3P, pose errors after a Sim3 alignment."""
    from services.evaluation import EvaluationError, evaluate_sfm, print_sfm_table

    try:
        summary = evaluate_sfm(scene, model, out)
    except EvaluationError as e:
        _fail(str(e))
    print_sfm_table(summary)
    if out is not None:
        typer.echo(f"wrote {out / 'summary.json'}")
