"""Aerial structure from motion: features, POS-guided matching, incremental mapping, georeferencing.

Steps (each a `shared.logging.stage`), all in pycolmap 4 on one COLMAP database:

1. images: the aerial images of an `images/` folder (`aerial/` inside) or of a flat folder (then
   named `aerial/<file>` through a symlink `out/images/aerial`); every image is decoded once to catch
   unreadable or truncated files; POS is checked against the images (both directions).
2. features: SIFT (pycolmap, downscaled to `max_image_size`, keypoints at full resolution) into the
   database, one camera for the set (intrinsics prior from cameras.json, else EXIF), or ALIKED
   (services.matching.features) imported into the database. ALIKED and LightGlue are not rotation invariant:
   with `features.upright = "pos"` each image is turned by the quarter turns that bring its view of
   the ground to north up (from its POS attitude), so that overlapping images are matched at about one
   in-plane orientation (the nadir images of a serpentine flight are 180 degrees apart from one line
   to the next otherwise); keypoints are stored in the image's own pixels. The POS
   positions go in as pose priors in a local ENU frame (LocalFrame at the mean POS position), with
   their covariance.
3. matching: pairs from the POS (pairing.py, `matching.pairs`): exhaustive, spatial neighbours, or
   overlapping ground footprints; "auto" matches up to `exhaustive_max` images exhaustively, else by
   footprints when attitudes and the terrain height are known, else by spatial neighbours. Geometric
   verification by pycolmap (LightGlue + pycolmap verification for ALIKED), then a POS check of the
   verified pairs (verify.py) removes those whose geometry contradicts the POS attitudes and positions.
4. mapping: pycolmap incremental mapping; with `use_prior_position` its bundle adjustment includes the
   POS positions (robust loss), so the models come out in the ENU frame. The largest model is kept.
5. georef: a robust similarity from its camera centres to the POS positions (georef.py), applied to
   the model, with residuals per image and a status: "ok", "suspect" (few inliers, large residuals or
   attitude errors; reasons listed) or "failed" (fewer than 3 inliers, or no estimate): then every
   output is still written, the model not georeferenced, and GeorefError is raised at the end.
6. outputs: out/sparse (COLMAP model, local ENU), pairs.txt, georef.json, report.json, cameras.geojson
   (WGS84) and, in the output CRS (conf export.out_crs; by default the POS CRS unless WGS84 lat/lon),
   cameras.csv and cameras.epsg<code>.geojson (export.py).
"""

from __future__ import annotations

import contextlib
import logging
import re
import shutil
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap
from tqdm import tqdm

from services.colmap_model import Camera
from services.conf import merge_conf
from services.pos import (
    DEFAULT_STD_XY,
    DEFAULT_STD_Z,
    LocalFrame,
    PosRecord,
    camera_from_exif,
    check_against_images,
    check_image,
    image_paths,
    match_names,
    read_exif,
    read_pos,
    read_pos_exif,
)
from shared.config import get_settings
from shared.images import ImageError
from shared.logging import stage

from . import export as export_mod
from . import georef as georef_mod
from . import pairing as pairing_mod
from . import verify as verify_mod
from .report import build_report, write_report

logger = logging.getLogger("midview.sfm")

_BASE: dict[str, Any] = {
    "features": {
        "type": "sift",
        "max_image_size": 1600,  # SIFT
        "max_num_features": 8192,  # SIFT
        "chunk": 4,  # SIFT: images per pycolmap call (progress)
        "upright": "pos",  # ALIKED: turn each image north up by quarter turns (POS attitude), or "none"
    },
    "matching": {
        **pairing_mod.default_conf,  # pairs: auto | exhaustive | spatial | footprint, and their settings
        "min_num_inliers": 15,
        "max_num_matches": 32768,
    },
    "verify": {k: v for k, v in verify_mod.default_conf.items() if not k.startswith("default_std")},
    "mapping": {
        "use_prior_position": True,
        "robust_prior": True,
        "min_model_size": 3,
        "seed": 0,
        "refine_intrinsics": None,  # None: refine unless cameras.json gave them
    },
    "camera": {"model": "SIMPLE_RADIAL"},
    "pos": {"default_std_xy": DEFAULT_STD_XY, "default_std_z": DEFAULT_STD_Z},  # when the POS gives none
    "georef": dict(georef_mod.default_conf),
    "export": dict(export_mod.default_conf),  # out_crs: "auto" (the POS CRS unless WGS84), None or a code
    "verify_images": "decode",  # "decode" (every image decoded once), "header" or "none"
    "colmap_log_level": 1,  # glog minloglevel while pycolmap runs: 0 info, 1 warnings, 2 errors
}


confs: dict[str, dict[str, Any]] = {
    "sift": merge_conf(_BASE, {"output": "sfm-sift"}),
    "sift-fast": merge_conf(
        _BASE, {"output": "sfm-sift-fast", "features": {"max_image_size": 1024, "max_num_features": 4096}}
    ),
    "aliked": merge_conf(
        _BASE,
        {
            "output": "sfm-aliked",
            "features": {"type": "aliked", "conf": "aliked"},
            "matching": {"matcher": {"name": "lightglue", "features": "aliked"}},
        },
    ),
}


class SfmError(RuntimeError):
    """The reconstruction could not be made (no model, too few images)."""


# -- helpers -----------------------------------------------------------------------------------
_GLOG_PREFIX = re.compile(r"^[IWEF]\d{8} [\d:.]+ +\d+ [^\]]*\] ")


@contextlib.contextmanager
def colmap_log_level(level: int, counts: dict[str, int] | None = None) -> Iterator[dict[str, int]]:
    """While pycolmap runs: glog's minloglevel `level`, and its warnings and errors written to a file
    instead of stderr (a bundle adjustment can print the same solver warning thousands of times). At
    the end each distinct message is logged once with its count; `counts` (message -> count, numbers
    written #), the dict yielded, holds them for a report."""
    import tempfile

    counts = {} if counts is None else counts
    log = pycolmap.logging
    saved = (log.minloglevel, log.alsologtostderr, log.stderrthreshold)
    with tempfile.TemporaryDirectory(prefix="midview-glog-") as tmp:
        log.minloglevel, log.alsologtostderr, log.stderrthreshold = level, False, 3  # FATAL only
        log.set_log_destination(log.WARNING, f"{tmp}/warnings.")
        try:
            yield counts
        finally:
            log.set_log_destination(log.WARNING, "")
            log.minloglevel, log.alsologtostderr, log.stderrthreshold = saved
            files = Path(tmp).glob("warnings.*")
            lines = {ln for f in files for ln in f.read_text(errors="replace").splitlines()}
            for line in sorted(lines):  # glog may write a line to its file twice: each line counts once
                if _GLOG_PREFIX.match(line):
                    message = re.sub(r"\d+", "#", _GLOG_PREFIX.sub("", line))[:300]
                    counts[message] = counts.get(message, 0) + 1
            for message, n in sorted(counts.items(), key=lambda kv: -kv[1]):
                logger.warning("pycolmap: %d x %s", n, message)


def _num_threads() -> int:
    return get_settings().num_threads or -1


def prepare_images(
    image_dir: str | Path, work_dir: str | Path, image_set: str = "aerial"
) -> tuple[Path, list[str]]:
    """(root, names) with root/name the image files of the set; a flat folder is linked as root/<set>."""
    image_dir = Path(image_dir)
    paths = image_paths(image_dir, flat_set=image_set)
    names = [n for n in paths if n.split("/", 1)[0] == image_set]
    if not names:
        raise ImageError(f"{image_dir}: no {image_set} images")
    if (image_dir / image_set).is_dir():
        return image_dir, names
    root = Path(work_dir) / "images"
    root.mkdir(parents=True, exist_ok=True)
    link = root / image_set
    if link.is_symlink() or link.exists():
        link.unlink()
    link.symlink_to(image_dir.resolve(), target_is_directory=True)
    return root, names


def verify_images(root: Path, names: list[str], mode: str = "decode") -> dict[str, tuple[int, int]]:
    """{name: (width, height)}; ImageError naming every unreadable or truncated image."""
    if mode == "none":
        return {}
    sizes, errors = {}, []
    for n in tqdm(names, desc="checking images", unit="img", leave=False):
        try:
            sizes[n] = check_image(root / n, decode=mode == "decode")
        except ImageError as e:
            errors.append(str(e))
    if errors:
        raise ImageError(f"{len(errors)} unusable image(s):\n  " + "\n  ".join(errors))
    return sizes


def select_records(
    records: list[PosRecord], names: list[str], image_set: str = "aerial"
) -> dict[str, PosRecord]:
    """POS records of the set's images, keyed by name; PosError for images without POS or POS without image.

    Records of other sets (e.g. ground rows of a scene's pos.csv) are ignored.
    """
    match_names(records, names)
    mine = [r for r in records if r.image_set in (image_set, "")]
    check_against_images(mine, names)
    return {r.name: r for r in mine}


def pos_crs(records: dict[str, PosRecord]) -> str | None:
    """The CRS the POS was given in (None when unknown, e.g. records built in code)."""
    codes = {r.crs for r in records.values() if r.crs is not None}
    if len(codes) > 1:
        logger.warning("POS records in several CRSs (%s): no output in the POS CRS", ", ".join(sorted(codes)))
        return None
    return next(iter(codes), None)


def local_frame(records: dict[str, PosRecord]) -> LocalFrame:
    """The ENU frame at the mean POS position."""
    a = np.array([(r.lat, r.lon, r.h) for r in records.values()])
    return LocalFrame(*(float(v) for v in a.mean(0)))


def camera_prior(
    cameras: dict[str, Camera] | None, root: Path, names: list[str], image_set: str
) -> tuple[Camera | None, str]:
    """Intrinsics prior of the set: cameras.json, else EXIF (35 mm focal length), else none."""
    if cameras and image_set in cameras:
        return cameras[image_set], "cameras.json"
    try:
        cam = camera_from_exif(read_exif(root / names[0]))
    except ImageError:
        cam = None
    return (cam, "exif") if cam is not None else (None, "pycolmap default")


# -- steps -------------------------------------------------------------------------------------
def check_sizes(sizes: dict[str, tuple[int, int]], camera: Camera | None, source: str) -> bool:
    """True when all images share one size; ValueError when a cameras.json camera does not fit them."""
    distinct = sorted(set(sizes.values()))
    if (
        camera is not None
        and source == "cameras.json"
        and distinct
        and distinct != [(camera.width, camera.height)]
    ):
        raise ValueError(
            f"cameras.json: the camera is {camera.width}x{camera.height}, the images are "
            + ", ".join(f"{w}x{h}" for w, h in distinct)
        )
    return len(distinct) <= 1


def extract_sift(
    conf: dict, db_path: Path, root: Path, names: list[str], camera: Camera | None, single_camera: bool = True
) -> None:
    """SIFT into the database, in chunks for progress; one camera for all images (or one per image)."""
    fconf = conf["features"]
    if not single_camera:
        camera = None  # pycolmap derives each image's prior from its own EXIF
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = camera.model if camera else conf["camera"]["model"]
    if camera is not None:
        reader.camera_params = ",".join(f"{p:.10g}" for p in camera.params)
    opts = pycolmap.FeatureExtractionOptions()
    opts.max_image_size = int(fconf["max_image_size"])
    opts.num_threads = _num_threads()
    opts.sift.max_num_features = int(fconf["max_num_features"])
    chunk = max(1, int(fconf.get("chunk", 4)))
    with tqdm(total=len(names), desc="SIFT", unit="img") as bar:
        for i in range(0, len(names), chunk):
            pycolmap.extract_features(
                db_path,
                root,
                image_names=names[i : i + chunk],
                camera_mode=pycolmap.CameraMode.SINGLE if single_camera else pycolmap.CameraMode.PER_IMAGE,
                reader_options=reader,
                extraction_options=opts,
            )
            if i == 0 and single_camera:  # later chunks reuse the camera of the first
                reader.existing_camera_id = 1
            bar.update(len(names[i : i + chunk]))


def write_pose_priors(
    db_path: Path, records: dict[str, PosRecord], frame: LocalFrame, std_xy: float, std_z: float
) -> int:
    """Replace the database's pose priors (pycolmap writes WGS84 ones from EXIF) by ENU positions."""
    db = pycolmap.Database.open(str(db_path))
    try:
        db.clear_pose_priors()
        n = 0
        for img in db.read_all_images():
            r = records.get(img.name)
            if r is None:
                continue
            sxy, sz = r.std_xy or std_xy, r.std_z or std_z
            prior = pycolmap.PosePrior(
                corr_data_id=img.data_id,
                position=frame.from_wgs84(r.lat, r.lon, r.h)[0],
                position_covariance=np.diag([sxy**2, sxy**2, sz**2]),
                coordinate_system=pycolmap.PosePriorCoordinateSystem.CARTESIAN,
            )
            db.write_pose_prior(prior)
            n += 1
    finally:
        db.close()
    return n


def match_sift(conf: dict, db_path: Path, mode: str, pairs_path: Path) -> None:
    """SIFT matching with pycolmap's geometric verification: exhaustive, or the pairs of `pairs_path`."""
    mconf = conf["matching"]
    mopts = pycolmap.FeatureMatchingOptions()
    mopts.num_threads = _num_threads()
    mopts.max_num_matches = int(mconf["max_num_matches"])
    vopts = pycolmap.TwoViewGeometryOptions()
    vopts.min_num_inliers = int(mconf["min_num_inliers"])
    if mode == "exhaustive":
        pycolmap.match_exhaustive(db_path, matching_options=mopts, verification_options=vopts)
    else:
        popts = pycolmap.ImportedPairingOptions()
        popts.match_list_path = pairs_path
        pycolmap.match_image_pairs(
            db_path, matching_options=mopts, pairing_options=popts, verification_options=vopts
        )


def camera_priors(
    names: list[str], camera: Camera | None, sizes: dict[str, tuple[int, int]], root: Path
) -> dict[str, Camera]:
    """Intrinsics prior per image for the footprints: the set's camera, else COLMAP's default prior
    (focal length 1.2 x the longer side, principal point at the centre)."""
    out = {}
    for n in names:
        if camera is not None:
            out[n] = camera
            continue
        w, h = sizes.get(n) or check_image(root / n)
        out[n] = Camera("SIMPLE_PINHOLE", w, h, [1.2 * max(w, h), w / 2, h / 2])
    return out


def unrotate_keypoints(kp: np.ndarray, k: int, width: int, height: int) -> np.ndarray:
    """Keypoints (COLMAP convention) of np.rot90(image, k) back in the (width x height) image."""
    kp = np.asarray(kp, np.float64)
    for t in range(k % 4, 0, -1):  # undo turn t; before it the image was (width, height) or turned
        w = width if (t - 1) % 2 == 0 else height
        kp = np.stack([w - kp[:, 1], kp[:, 0]], 1)
    return kp.astype(np.float32)


def aliked_conf(conf: dict) -> dict:
    """The services.matching.features conf of the ALIKED path (a name or a dict) with `features` overrides."""
    from services import matching

    fc = conf["features"]
    base = matching.feature_confs[fc["conf"]] if isinstance(fc["conf"], str) else fc["conf"]
    model = {**base["model"], **fc.get("model", {})}
    pre = {**base["preprocessing"], **fc.get("preprocessing", {})}
    out = {**base, "model": model, "preprocessing": pre}
    if model != base["model"] or pre != base["preprocessing"]:
        out["output"] = f"{base['output']}-sfm"
    return out


def extract_aliked(
    conf: dict, root: Path, names: list[str], turns: dict[str, int], cache: Path
) -> dict[str, dict]:
    """ALIKED of every image, each turned by its quarter turns (`turns`): unturned images through the
    services.matching.features cache, turned ones in memory. Per image the features with keypoints in
    the turned image's pixels (for LightGlue, with its size), and `image_keypoints` and `own_size` of
    the image."""
    from services import matching
    from shared.images import read_image

    fconf = aliked_conf(conf)
    plain = [n for n in names if turns.get(n, 0) == 0]
    if plain:
        matching.extract_features(fconf, root, plain, cache)
    feats: dict[str, dict] = {}
    for n in tqdm(names, desc="ALIKED", unit="img", disable=not len(plain) < len(names)):
        k = turns.get(n, 0)
        if k == 0:
            f = matching.load_features(cache, n)
            f["image_keypoints"], f["own_size"] = f["keypoints"], f["image_size"]
        else:
            image = read_image(root / n, grayscale=fconf["preprocessing"].get("grayscale", False))
            h, w = image.shape[:2]
            f = matching.extract(fconf, np.ascontiguousarray(np.rot90(image, k)))
            f["image_size"] = np.array([w, h] if k % 2 == 0 else [h, w], np.int64)
            f["image_keypoints"], f["own_size"] = (
                unrotate_keypoints(f["keypoints"], k, w, h),
                np.array([w, h]),
            )
        feats[n] = f
    return feats


def write_aliked_database(
    conf: dict,
    db_path: Path,
    names: list[str],
    camera: Camera | None,
    feats: dict[str, dict],
) -> dict[str, int]:
    """Cameras (one per image size, the prior when given), rigs, frames, images and keypoints; {name: id}."""
    db = pycolmap.Database.open(str(db_path))
    ids: dict[str, int] = {}
    try:
        cam_ids: dict[tuple[int, int], tuple[int, int]] = {}
        for n in names:
            w, h = (int(v) for v in feats[n]["own_size"])
            if (w, h) not in cam_ids:
                cam = camera or Camera(conf["camera"]["model"], w, h, [1.2 * max(w, h), w / 2, h / 2, 0.0])
                pcam = cam.to_pycolmap(camera_id=0)
                pcam.has_prior_focal_length = camera is not None
                pcam.camera_id = db.write_camera(pcam)
                rig = pycolmap.Rig()
                rig.add_ref_sensor(pcam.sensor_id)
                cam_ids[(w, h)] = (pcam.camera_id, db.write_rig(rig))
            cam_id, rig_id = cam_ids[(w, h)]
            image = pycolmap.Image(name=n, camera_id=cam_id)
            image.image_id = db.write_image(image)
            frame = pycolmap.Frame(rig_id=rig_id)
            frame.add_data_id(image.data_id)
            db.write_frame(frame)
            db.write_keypoints(image.image_id, np.ascontiguousarray(feats[n]["image_keypoints"], np.float32))
            ids[n] = image.image_id
    finally:
        db.close()
    return ids


def match_aliked(
    conf: dict,
    db_path: Path,
    ids: dict[str, int],
    feats: dict[str, dict],
    pairs: list[tuple[str, str]],
) -> None:
    """LightGlue on each pair (each image at its turn), into the database; then pycolmap's
    geometric verification."""
    from services.matching import match_features

    db = pycolmap.Database.open(str(db_path))
    try:
        for a, b in tqdm(pairs, desc="LightGlue", unit="pair"):
            m, _ = match_features(feats[a], feats[b], conf["matching"]["matcher"])
            db.write_matches(ids[a], ids[b], np.ascontiguousarray(m, np.uint32).reshape(-1, 2))
    finally:
        db.close()
    vopts = pycolmap.TwoViewGeometryOptions()
    vopts.min_num_inliers = int(conf["matching"]["min_num_inliers"])
    pycolmap.geometric_verification(db_path, two_view_geometry_options=vopts)


def run_mapping(
    conf: dict, db_path: Path, root: Path, out_dir: Path, n_images: int, refine_intrinsics: bool
) -> dict[int, pycolmap.Reconstruction]:
    """pycolmap incremental mapping into out_dir/<k>; a progress bar counts registered images."""
    mconf = conf["mapping"]
    o = pycolmap.IncrementalPipelineOptions()
    o.num_threads = _num_threads()
    o.random_seed = int(mconf["seed"])
    o.mapper.random_seed = int(mconf["seed"])
    o.min_model_size = min(int(mconf["min_model_size"]), n_images)
    o.use_prior_position = bool(mconf["use_prior_position"])
    o.use_robust_loss_on_prior_position = bool(mconf["robust_prior"])
    o.ba_refine_focal_length = refine_intrinsics
    o.ba_refine_extra_params = refine_intrinsics
    o.mapper.abs_pose_refine_focal_length = refine_intrinsics
    o.mapper.abs_pose_refine_extra_params = refine_intrinsics
    if out_dir.exists():
        shutil.rmtree(out_dir)
    out_dir.mkdir(parents=True)
    with tqdm(total=n_images, desc="mapping", unit="img") as bar:

        def registered() -> None:
            bar.update(1) if bar.n < bar.total else None

        models = pycolmap.incremental_mapping(
            db_path,
            root,
            out_dir,
            o,
            initial_image_pair_callback=lambda: bar.update(2),
            next_image_callback=registered,
        )
    return dict(models)


def _database_stats(db_path: Path, min_inliers: int) -> dict:
    db = pycolmap.Database.open(str(db_path))
    try:
        _, counts = db.read_two_view_geometry_num_inliers()
        return {
            "num_keypoints": int(db.num_keypoints()),
            "mean_keypoints": float(db.num_keypoints() / max(db.num_images(), 1)),
            "num_matched_pairs": int(db.num_matched_image_pairs()),
            "num_verified_pairs": int(sum(c >= min_inliers for c in counts)),
        }
    finally:
        db.close()


def _log_matching(db_path: Path, conf: dict, pairing: str, seconds: float) -> dict:
    stats = _database_stats(db_path, conf["matching"]["min_num_inliers"])
    logger.info(
        "%s matching: %d verified of %d matched pairs in %.1f s",
        pairing,
        stats["num_verified_pairs"],
        stats["num_matched_pairs"],
        seconds,
    )
    return stats


# -- main --------------------------------------------------------------------------------------
@dataclass
class AerialInputs:
    """The images, POS and camera priors of one aerial SfM, and its pairs (the `sfm:images` step)."""

    root: Path  # the images' folder (set/NAME)
    names: list[str]
    pos: dict[str, PosRecord]
    pos_source: str
    frame: Any  # services.pos.frames.LocalFrame: the ENU frame at the POS centroid
    in_crs: str | None
    crs_doc: dict[str, Any]
    camera: Camera | None  # one camera for all images, None: one per image from its EXIF
    cam_source: str
    single_camera: bool
    pair_mode: str
    name_pairs: list[tuple[str, str]]
    pairs_path: Path

    @property
    def pairing(self) -> str:
        return f"{self.pair_mode} ({len(self.name_pairs)} pairs)"


def load_inputs(
    conf: dict[str, Any],
    image_dir: str | Path,
    out_dir: Path,
    pos_records: list[PosRecord] | str | Path | None,
    cameras: dict[str, Camera] | None,
    image_set: str,
) -> AerialInputs:
    """The images (checked), their POS, output CRS, camera prior and the pairs to match."""
    root, names = prepare_images(image_dir, out_dir, image_set)
    sizes = verify_images(root, names, conf["verify_images"])
    if pos_records is None:
        records, pos_source = read_pos_exif(root, names), "exif"
    elif isinstance(pos_records, str | Path):
        records, pos_source = read_pos(pos_records), str(pos_records)
    else:
        records, pos_source = list(pos_records), "records"
    pos = select_records(records, names, image_set)
    frame = local_frame(pos)
    in_crs = pos_crs(pos)
    out_crs = export_mod.resolve_crs(conf["export"]["out_crs"], in_crs)  # CRSError before any work
    files = export_mod.output_files(out_crs, conf["export"]["footprints"])
    camera, cam_source = camera_prior(cameras, root, names, image_set)
    single_camera = check_sizes(sizes, camera, cam_source)
    if not single_camera:
        logger.warning("the images differ in size: one camera per image, priors from their EXIF")
        camera, cam_source = None, "exif per image"
    cams_by_name = camera_priors(names, camera, sizes, root)
    pair_mode, name_pairs = pairing_mod.get_pairs(conf["matching"], names, pos, frame, cams_by_name)
    pairs_path = pairing_mod.write_pairs(out_dir / "pairs.txt", name_pairs)
    logger.info("%s pairing: %d pairs -> %s", pair_mode, len(name_pairs), pairs_path)
    logger.info(
        "%d %s images under %s, POS from %s, camera prior from %s; ENU origin %.7f %.7f %.2f",
        len(names),
        image_set,
        root,
        pos_source,
        cam_source,
        frame.lat0,
        frame.lon0,
        frame.h0,
    )
    crs_doc = {"pos": in_crs, "output": out_crs, "files": files}
    return AerialInputs(
        root, names, pos, pos_source, frame, in_crs, crs_doc, camera, cam_source, single_camera, pair_mode,
        name_pairs, pairs_path,
    )  # fmt: skip


def _std_conf(conf: dict) -> dict[str, float]:
    return {"default_std_xy": conf["pos"]["default_std_xy"], "default_std_z": conf["pos"]["default_std_z"]}


def features_and_matches(
    conf: dict, inp: AerialInputs, db_path: Path, out_dir: Path, timings: dict[str, float]
) -> tuple[dict, dict, dict]:
    """The database: features (SIFT or ALIKED) with the POS as pose priors, matches of the pairs checked
    against the POS. Returns (database stats, the pairs' check, report entries of the feature path)."""
    for p in (db_path, db_path.with_name(db_path.name + "-wal"), db_path.with_name(db_path.name + "-shm")):
        p.unlink(missing_ok=True)
    ftype = conf["features"]["type"]
    if ftype not in ("sift", "aliked"):
        raise ValueError(f"unknown feature type {ftype!r} (sift or aliked)")
    std = _std_conf(conf)
    extra: dict[str, Any] = {}
    with stage("sfm:features", logger):
        t0 = time.perf_counter()
        if ftype == "sift":
            extract_sift(conf, db_path, inp.root, inp.names, inp.camera, inp.single_camera)
            ids, feats = None, None
        else:
            ids, feats, extra["aliked"] = _aliked_features(conf, inp, db_path, out_dir)
        write_pose_priors(db_path, inp.pos, inp.frame, std["default_std_xy"], std["default_std_z"])
        timings["features"] = time.perf_counter() - t0
        turned = f" ({extra['aliked']['turned_images']} turned north up)" if "aliked" in extra else ""
        logger.info(
            "%d images%s, %.0f keypoints per image in %.1f s",
            len(inp.names),
            turned,
            _database_stats(db_path, 0)["mean_keypoints"],
            timings["features"],
        )
    with stage("sfm:matching", logger):
        t0 = time.perf_counter()
        if ftype == "sift":
            match_sift(conf, db_path, inp.pair_mode, inp.pairs_path)
        else:
            match_aliked(conf, db_path, ids, feats, inp.name_pairs)
        pair_check = verify_mod.check_pairs(db_path, inp.pos, inp.frame, {**conf["verify"], **std})
        timings["matching"] = time.perf_counter() - t0
        dbstats = _log_matching(db_path, conf, inp.pairing, timings["matching"])
    return dbstats, pair_check, extra


def _aliked_features(conf: dict, inp: AerialInputs, db_path: Path, out_dir: Path) -> tuple[dict, dict, dict]:
    """ALIKED features of the images (each turned north up by the POS when `upright`), written to the
    database: (image ids, features, report entry)."""
    turns = pairing_mod.upright_turns(inp.pos, inp.names) if conf["features"]["upright"] == "pos" else {}
    cache = out_dir / f"{aliked_conf(conf)['output']}.h5"
    feats = extract_aliked(conf, inp.root, inp.names, turns, cache)
    ids = write_aliked_database(conf, db_path, inp.names, inp.camera, feats)
    turned = sum(k != 0 for k in turns.values())
    return ids, feats, {"turned_images": turned, "turns": {n: k for n, k in turns.items() if k}}


def map_images(
    conf: dict, inp: AerialInputs, db_path: Path, out_dir: Path, dbstats: dict, timings: dict[str, float]
) -> tuple[dict[int, pycolmap.Reconstruction], int]:
    """Incremental mapping (intrinsics refined unless cameras.json gave them): (models, the largest's key)."""
    t0 = time.perf_counter()
    refine = conf["mapping"]["refine_intrinsics"]
    refine = inp.camera is None or inp.cam_source != "cameras.json" if refine is None else bool(refine)
    models = run_mapping(conf, db_path, inp.root, out_dir / "models", len(inp.names), refine)
    timings["mapping"] = time.perf_counter() - t0
    if not models:
        raise SfmError(
            f"no model: {dbstats['num_verified_pairs']} verified pairs among {len(inp.names)} images"
        )
    best = max(models, key=lambda k: models[k].num_reg_images())
    rec = models[best]
    logger.info(
        "%d model(s); the largest registers %d/%d images, %d points in %.1f s",
        len(models),
        rec.num_reg_images(),
        len(inp.names),
        rec.num_points3D(),
        timings["mapping"],
    )
    return models, best


def georeference_model(
    conf: dict, rec: pycolmap.Reconstruction, inp: AerialInputs, out_dir: Path
) -> tuple[georef_mod.Georef | None, dict, Path]:
    """Georeference the model by the POS and write it (kept whatever the georeference gave) with
    georef.json: (georef or None when it failed, its summary, the sparse folder)."""
    sigma = float(np.median([inp.pos[n].std_xy or conf["pos"]["default_std_xy"] for n in inp.names]))
    geo: georef_mod.Georef | None = None
    try:
        geo = georef_mod.georeference(rec, inp.pos, inp.frame, sigma, conf["georef"])
        gsum = georef_mod.summary(geo, conf["georef"])
    except georef_mod.GeorefError as e:
        gsum = georef_mod.failed_summary(str(e))
    if gsum["status"] == "failed":
        inp.crs_doc["files"] = []
    sparse = out_dir / "sparse"
    if sparse.exists():
        shutil.rmtree(sparse)
    sparse.mkdir(parents=True)
    rec.write(str(sparse))
    georef_mod.write_georef(out_dir / "georef.json", geo, inp.frame, inp.crs_doc, gsum)
    if geo is not None:
        logger.info(
            "georeferenced by %s: residuals mean %.2f m, median %.2f m, max %.2f m (%d/%d inliers)",
            geo.method,
            gsum["residual_m"]["mean"],
            gsum["residual_m"]["median"],
            gsum["residual_m"]["max"],
            gsum["num_inliers"],
            gsum["num_images"],
        )
    if gsum["status"] != "ok":
        logger.warning("georeference %s: %s", gsum["status"], "; ".join(gsum["reasons"]))
    return geo, gsum, sparse


def export_and_report(
    conf: dict,
    inp: AerialInputs,
    models: dict,
    best: int,
    geo: georef_mod.Georef | None,
    gsum: dict,
    db_path: Path,
    out_dir: Path,
    timings: dict[str, float],
    extra: dict[str, Any],
) -> dict:
    """Camera exports (none after a failed georeference, nor stale ones of an earlier run) and
    report.json; the report."""
    rec = models[best]
    if geo is None or gsum["status"] == "failed":
        for p in (out_dir / "cameras.geojson", out_dir / "cameras.csv", *out_dir.glob("cameras.epsg*")):
            p.unlink(missing_ok=True)
    else:
        residuals = {n: float(np.linalg.norm(v)) for n, v in geo.residuals.items()}
        export_mod.main(conf["export"], rec, inp.frame, out_dir, inp.in_crs, residuals)
    ftype = conf["features"]["type"]
    report = build_report(
        rec,
        inp.names,
        db_path,
        models,
        best,
        {**gsum, "method": geo and geo.method, "condition": geo and geo.condition},
        timings,
        extra={
            "conf": conf.get("output", ftype),
            "features": ftype,
            "pairing": inp.pairing,
            "pos_source": inp.pos_source,
            "camera_prior": inp.cam_source,
            "frame": {"lat0": inp.frame.lat0, "lon0": inp.frame.lon0, "h0": inp.frame.h0},
            "crs": inp.crs_doc,
            **extra,
        },
        min_inliers=conf["matching"]["min_num_inliers"],
    )
    write_report(out_dir / "report.json", report)
    for u in report["unregistered"]:
        logger.warning("not registered: %s (%s)", u["name"], u["reason"])
    logger.info(
        "NRI %s, N3P %d, reprojection error %.2f px -> %s",
        report["NRI"],
        report["num_points3D"],
        report["mean_reprojection_error_px"],
        out_dir / "sparse",
    )
    return report


def main(
    conf: dict[str, Any],
    image_dir: str | Path,
    out_dir: str | Path,
    pos_records: list[PosRecord] | str | Path | None = None,
    cameras: dict[str, Camera] | None = None,
    image_set: str = "aerial",
) -> Path:
    """Reconstruct and georeference the aerial images of `image_dir`; returns out_dir/sparse.

    `pos_records`: records, or a POS file (any format of services.pos.read_pos); default: the EXIF of
    the images. `cameras`: intrinsics per set (cameras.json); used as given (not refined).
    """
    conf = merge_conf(_BASE, conf)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    timings: dict[str, float] = {}
    t_all = time.perf_counter()
    with stage("sfm:images", logger):
        t0 = time.perf_counter()
        inp = load_inputs(conf, image_dir, out_dir, pos_records, cameras, image_set)
        timings["images"] = time.perf_counter() - t0
    db_path = out_dir / "database.db"
    with colmap_log_level(conf["colmap_log_level"]) as warnings:
        dbstats, pair_check, extra = features_and_matches(conf, inp, db_path, out_dir, timings)
        with stage("sfm:mapping", logger):
            models, best = map_images(conf, inp, db_path, out_dir, dbstats, timings)
    with stage("sfm:georef", logger):
        t0 = time.perf_counter()
        geo, gsum, sparse = georeference_model(conf, models[best], inp, out_dir)
        timings["georef"] = time.perf_counter() - t0
    with stage("sfm:report", logger):
        timings["total"] = time.perf_counter() - t_all
        extra = {"database": dbstats, "pair_check": pair_check, **extra, "colmap_warnings": warnings}
        export_and_report(conf, inp, models, best, geo, gsum, db_path, out_dir, timings, extra)
    if gsum["status"] == "failed":
        raise georef_mod.GeorefError(
            f"georeferencing failed: {'; '.join(gsum['reasons'])}. The model is kept in {sparse} "
            f"(not georeferenced), the report in {out_dir / 'report.json'}"
        )
    return sparse
