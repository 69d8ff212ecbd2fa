"""Export a match file (shared/matchfile.py) to a COLMAP database for pycolmap's mappers.

pycolmap 4 databases model rigs and frames: every camera gets a trivial rig (the camera as its
reference sensor) and every image a frame of that rig holding just the image, as COLMAP's own
feature extractor does.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pycolmap

from services.colmap_model import Camera
from shared.matchfile import MatchFile

logger = logging.getLogger(__name__)


def _remove_database(path: Path) -> None:
    for p in (path, path.with_name(path.name + "-wal"), path.with_name(path.name + "-shm")):
        p.unlink(missing_ok=True)


def _write_cameras(
    db: pycolmap.Database, cameras: dict[str, Camera], sets: list[str]
) -> dict[str, tuple[int, int]]:
    """One camera and one trivial rig per set: {set: (camera_id, rig_id)}."""
    ids = {}
    for s in sets:
        if s not in cameras:
            raise KeyError(f"no camera for image set {s!r} (cameras has {sorted(cameras)})")
        cam = cameras[s].to_pycolmap(camera_id=0)
        cam.camera_id = db.write_camera(cam)
        rig = pycolmap.Rig()
        rig.add_ref_sensor(cam.sensor_id)
        ids[s] = (cam.camera_id, db.write_rig(rig))
    return ids


def _write_image(db: pycolmap.Database, name: str, camera_id: int, rig_id: int) -> int:
    """An image and its single-image frame; returns the image id."""
    image = pycolmap.Image(name=name, camera_id=camera_id)
    image.image_id = db.write_image(image)
    frame = pycolmap.Frame(rig_id=rig_id)
    frame.add_data_id(image.data_id)
    db.write_frame(frame)
    return image.image_id


def export_to_database(
    match_file: Path, database_path: Path, cameras: dict[str, Camera], only_inliers: bool = False
) -> Path:
    """Write a fresh COLMAP database from a match file and return its path.

    Cameras: one per set (the first component of the image name), from `cameras` (as read by
    `read_cameras_json`); their size must be the image size stored in the match file. Keypoints are
    copied as they are (both use COLMAP's pixel convention). Per pair, the matches (only the stored
    inliers with `only_inliers`) and an UNCALIBRATED two-view geometry whose inlier matches are the
    stored inliers, or all matches when the match file stores none (the mappers re-estimate the
    relative pose from them).
    """
    database_path = Path(database_path)
    database_path.parent.mkdir(parents=True, exist_ok=True)
    _remove_database(database_path)
    with MatchFile(match_file, "r") as mf:
        names = mf.image_names()
        sets = sorted({n.split("/", 1)[0] for n in names})
        db = pycolmap.Database.open(str(database_path))
        try:
            cam_rig = _write_cameras(db, cameras, sets)
            image_ids = {}
            for name in names:
                s = name.split("/", 1)[0]
                cam = cameras[s]
                if mf.image_size(name) != (cam.width, cam.height):
                    raise ValueError(
                        f"{name}: image size {mf.image_size(name)} in the match file, "
                        f"camera {s!r} is {cam.width}x{cam.height}"
                    )
                image_ids[name] = _write_image(db, name, *cam_rig[s])
                db.write_keypoints(image_ids[name], np.ascontiguousarray(mf.keypoints(name), np.float32))
            n_pairs = 0
            for pm in mf.iter_pairs():
                id0, id1 = image_ids[pm.name0], image_ids[pm.name1]
                if db.exists_matches(id0, id1):
                    logger.warning(
                        "pair %s / %s stored twice in %s; keeping the first", pm.name0, pm.name1, match_file
                    )
                    continue
                matches = np.asarray(pm.matches, np.uint32).reshape(-1, 2)
                inliers = matches if pm.inliers is None else matches[np.asarray(pm.inliers, bool)]
                db.write_matches(id0, id1, np.ascontiguousarray(inliers if only_inliers else matches))
                tvg = pycolmap.TwoViewGeometry(
                    config=pycolmap.TwoViewGeometryConfiguration.UNCALIBRATED,
                    inlier_matches=np.ascontiguousarray(inliers),
                )
                db.write_two_view_geometry(id0, id1, tvg)
                n_pairs += 1
        finally:
            db.close()
    logger.info("%s: %d images, %d pairs from %s", database_path, len(names), n_pairs, match_file)
    return database_path
