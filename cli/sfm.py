"""`midview sfm`: reconstruct and georeference the aerial images (services/sfm)."""

from __future__ import annotations

from pathlib import Path

import typer


def _fail(message: str) -> None:
    typer.secho(message, fg="red", err=True)
    raise typer.Exit(2)


def resolve_inputs(
    images: Path, pos: Path | None, cameras: Path | None
) -> tuple[Path, Path | None, Path | None]:
    """A synthetic scene folder (images/, pos.csv, cameras.json inside) stands for its parts."""
    if (images / "images").is_dir() and not (images / "aerial").is_dir():
        if pos is None and (images / "pos.csv").is_file():
            pos = images / "pos.csv"
        if cameras is None and (images / "cameras.json").is_file():
            cameras = images / "cameras.json"
        images = images / "images"
    return images, pos, cameras


def sfm(
    images: Path = typer.Argument(
        ...,
        metavar="IMAGES",
        help="images/ folder (aerial/ inside), a flat folder of aerial images, or a scene folder",
    ),
    out: Path = typer.Argument(
        ..., metavar="OUT", help="output folder (sparse/, georef.json, report.json, ...)"
    ),
    pos: Path = typer.Option(
        None, "--pos", help="POS file: .csv, .json or ODM geo.txt (default: the images' EXIF)"
    ),
    features: str = typer.Option("sift", "--features", help="sift, sift-fast or aliked"),
    cameras: Path = typer.Option(
        None, "--cameras", help="cameras.json with intrinsics per set (not refined)"
    ),
    max_image_size: int = typer.Option(
        None, "--max-image-size", help="downscale images for SIFT to this side"
    ),
    exhaustive_max: int = typer.Option(
        None, "--exhaustive-max", help="match exhaustively up to this many images"
    ),
    pairs: str = typer.Option(
        None, "--pairs", help="image pairs: auto, exhaustive, spatial or footprint (default: auto)"
    ),
    ground_height: float = typer.Option(
        None, "--ground-height", help="footprint pairs: terrain height (ellipsoidal, metres)"
    ),
    height_above_ground: float = typer.Option(
        None,
        "--height-above-ground",
        help="footprint pairs: flight height above the terrain (metres); default: the POS's relative "
        "altitude (DJI XMP)",
    ),
    no_priors: bool = typer.Option(
        False, "--no-priors", help="do not use POS positions in bundle adjustment"
    ),
    out_crs: str = typer.Option(
        None,
        "--out-crs",
        help="also write camera positions in this CRS (EPSG:NNNN; 'none': WGS84 only); "
        "default: the POS CRS unless it is WGS84 latitude/longitude",
    ),
) -> None:
    """Aerial SfM: SIFT (or ALIKED) features, POS-guided matching (exhaustive, spatial neighbours or
    footprint overlap), incremental mapping, georeferencing.

    Writes OUT/sparse (COLMAP model in the local ENU frame), OUT/georef.json, OUT/report.json,
    OUT/cameras.geojson (WGS84 camera positions and footprints) and, in the output CRS, OUT/cameras.csv
    (POS CSV format) and OUT/cameras.epsg<code>.geojson.
    """
    from services.colmap_model import read_cameras_json
    from services.pos import PosError
    from services.sfm import GeorefError, SfmError, confs, main
    from shared.images import ImageError

    if features not in confs:
        _fail(f"unknown --features {features!r}: use one of {', '.join(confs)}")
    images, pos, cameras = resolve_inputs(images, pos, cameras)
    conf = {**confs[features]}
    if max_image_size is not None:
        conf["features"] = {**conf["features"], "max_image_size": max_image_size}
    matching = {**conf["matching"], "footprint": {**conf["matching"]["footprint"]}}
    if exhaustive_max is not None:
        matching["exhaustive_max"] = exhaustive_max
    if pairs is not None:
        matching["pairs"] = pairs
    if ground_height is not None:
        matching["footprint"]["ground_h"] = ground_height
    if height_above_ground is not None:
        matching["footprint"]["height_above_ground"] = height_above_ground
    conf["matching"] = matching
    if no_priors:
        conf["mapping"] = {**conf["mapping"], "use_prior_position": False}
    if out_crs is not None:
        conf["export"] = {**conf["export"], "out_crs": out_crs}
    try:
        cams = read_cameras_json(cameras) if cameras is not None else None
        sparse = main(conf, images, out, pos, cams)
    except GeorefError as e:
        if (out / "report.json").is_file():
            print_summary(out)
        _fail(str(e))
    except (PosError, ImageError, SfmError, ValueError) as e:
        _fail(str(e))
    report = print_summary(out)
    g = report["georef"]
    if g["status"] != "ok":
        typer.secho(f"warning: the georeference is {g['status']}:", fg="yellow", err=True)
        for reason in g["reasons"]:
            typer.secho(f"  {reason}", fg="yellow", err=True)
    crs = report["crs"]
    if crs["output"]:
        typer.echo(f"camera positions in {crs['output']} (POS CRS {crs['pos'] or 'WGS84'})")
    files = ", ".join(str(out / f) for f in ("georef.json", "report.json", *crs["files"]))
    typer.echo(f"wrote {sparse}, {files}")


def print_summary(out: Path) -> dict:
    """Print the key figures of OUT/report.json (and why images did not register); return the report."""
    import json

    report = json.loads((out / "report.json").read_text())
    g = report["georef"]["residual_m"]
    georef = (
        "no georeference"
        if g["mean"] is None
        else f"georef residual mean {g['mean']:.2f} m / max {g['max']:.2f} m"
    )
    typer.echo(
        f"NRI {report['NRI']}, N3P {report['num_points3D']}, reprojection error "
        f"{report['mean_reprojection_error_px']:.2f} px, {georef} ({report['georef']['status']})"
    )
    unc, lv = report["georef"].get("uncertainty") or {}, report["georef"].get("levels") or {}
    if unc:
        typer.echo(
            f"georeference: {report['georef'].get('method')}; 1-sigma tilt {unc['tilt_deg']:.2f} deg, "
            f"heading {unc['heading_deg']:.2f} deg, scale {100 * unc['scale_rel']:.2f}%"
            + (
                f"; flight plane {lv['flight_plane_tilt_deg']:.2f} deg from the vertical"
                if lv.get("flight_plane_tilt_deg") is not None
                else ""
            )
        )
    for u in report["unregistered"]:
        typer.echo(f"  not registered: {u['name']}: {u['reason']}")
    return report
