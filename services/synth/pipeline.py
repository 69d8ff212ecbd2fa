"""Render a synthetic aerial + ground survey with exact ground truth into a scene folder
(docs/formats.md, "Synthetic scene folder")."""

from __future__ import annotations

import json
import logging
import math
import shutil
import time
from pathlib import Path

import h5py
import numpy as np
from tqdm import tqdm

from services.colmap_model import Camera, write_cameras_json, write_model
from services.pos import LocalFrame, PosRecord, write_pos_csv
from shared.logging import stage

from .cameras import View, aerial_views, ground_views, pinhole, small_rotation
from .gt import DEPTH_FILE, depth_key, pixel_grid, visible_fraction, write_covisible
from .imaging import develop, encode_jpeg, list_photos, photo_atlas, srgb_to_linear_lut
from .materials import L_AMB, L_CLOUD, L_HAZEC, L_HAZED, L_HOR, L_SHADOW, L_SUN, L_SUNC, L_ZEN, NLIGHT
from .scene import Scene, make_scene
from .walls import wall_atlas

log = logging.getLogger("midview.synth")

OUTPUTS = ("images/aerial", "images/ground", "gt", "pos.csv", "cameras.json")


def sun_vector(azimuth: float, elevation: float) -> np.ndarray:
    """Unit vector towards the sun in ENU; azimuth clockwise from north, degrees."""
    a, e = math.radians(azimuth), math.radians(elevation)
    return np.array([math.sin(a) * math.cos(e), math.cos(a) * math.cos(e), math.sin(e)])


def light_array(conf: dict) -> np.ndarray:
    """The kernels' lighting row (materials.L_*) of a lighting conf."""
    L = np.zeros(NLIGHT)
    L[L_SUN : L_SUN + 3] = sun_vector(conf["sun_azimuth"], conf["sun_elevation"])
    for k, key in (
        (L_SUNC, "sun"),
        (L_AMB, "ambient"),
        (L_ZEN, "zenith"),
        (L_HOR, "horizon"),
        (L_HAZEC, "haze"),
    ):
        L[k : k + 3] = conf[key]
    L[L_HAZED] = conf["haze_distance"]
    L[L_SHADOW] = 1.0 if conf["shadows"] else 0.0
    L[L_CLOUD] = conf["clouds"]
    return L


class Renderer:
    """Holds the scene arrays for the numba kernel; `__call__` renders one view."""

    def __init__(self, scene: Scene, photos: tuple, seed: int, grid_cell: float = 4.0):
        self.scene = scene
        self.grid_cell = grid_cell
        self._captures: dict[str, tuple[Scene, tuple]] = {}
        self.photos = photos[:3]
        self.lut = srgb_to_linear_lut()
        self.seed = int(seed)

    def capture(self, name: str) -> tuple[Scene, tuple]:
        """The scene as capture `name` saw it (Scene.for_capture) and its grid, made once."""
        if name not in self._captures:
            scene = self.scene.for_capture(name)
            same = next((v for v in self._captures.values() if v[0] is scene), None)
            self._captures[name] = same or (scene, scene.grid(self.grid_cell))
        return self._captures[name]

    def __call__(
        self, view: View, cam: Camera, light: np.ndarray, ss: int, capture: str | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """-> linear RGB radiance (H, W, 3) float32 and z-depth (H, W) float32 (0 = sky) of the scene as
        capture `capture` saw it (default: the view's image set)."""
        from .kernels import render

        s, (gmeta, cstart, citems) = self.capture(capture or view.image_set)
        fx, fy, cx, cy = cam.params
        h, w = cam.height, cam.width
        img = np.zeros((h, w, 3), np.float32)
        depth = np.zeros((h, w), np.float32)
        rows = np.concatenate([np.arange(k, h, 16) for k in range(16)]).astype(np.int64)
        atlas, aoff, adim = self.photos
        render(
            np.ascontiguousarray(view.C, np.float64), np.ascontiguousarray(view.R, np.float64),
            float(fx), float(fy), float(cx), float(cy), int(ss), rows,
            s.boxes, s.bmat, s.bpar, s.sph, s.smat, s.spar, gmeta, cstart, citems,
            s.zone, s.zmeta, s.lay, atlas, aoff, adim, self.lut, light, self.seed, img, depth,
        )  # fmt: skip
        return img, depth


def build_survey(
    conf: dict, seed: int, textures_dir: Path | None
) -> tuple[tuple, Scene, list[View], list[View], np.random.Generator]:
    """The textures, scene and cameras of preset `conf` with `seed` (the same every time): (photos for
    the kernels, the scene without the clutter in the ground cameras' way, aerial views, ground views,
    the random stream of the POS noise). Facades take whole photos of textures_dir, or with a
    `wall_photos` share in the preset's scene, brick walls cut from them (services.synth.walls)."""
    r_scene, r_cam, r_pos = (np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(3))
    tex = Path(textures_dir) if textures_dir is not None else None
    walls = None
    if tex is not None and conf["scene"].get("wall_photos", 0.0) > 0.0:
        photos = wall_atlas(tex)
        walls = photos[3]
    else:
        photos = photo_atlas(tex)
    photo = tex is not None and walls is None and conf["scene"].get("photo_facades", True)
    scene = make_scene(conf["scene"], r_scene, photo=photo, walls=walls)
    aerial = aerial_views(conf["aerial"], scene, r_cam)
    ground = ground_views(conf["ground"], scene, r_cam)
    scene = scene.drop_clutter_near(np.array([g.C for g in ground]), conf["render"]["clearance"])
    return photos[:3], scene, aerial, ground, r_pos


def _prepare(out_dir: Path, overwrite: bool) -> None:
    if out_dir.exists() and not out_dir.is_dir():
        raise FileExistsError(f"{out_dir} exists and is not a folder")
    if out_dir.is_dir() and any(out_dir.iterdir()):
        if not overwrite:
            raise FileExistsError(f"{out_dir} is not empty (overwrite it with force/--force)")
        for rel in OUTPUTS:
            p = out_dir / rel
            if p.is_dir():
                shutil.rmtree(p)
            elif p.exists():
                p.unlink()
    for d in ("images/aerial", "images/ground", "gt"):
        (out_dir / d).mkdir(parents=True, exist_ok=True)


def noisy_pos(views: list[View], conf: dict, frame: LocalFrame, rng: np.random.Generator) -> list[PosRecord]:
    """POS records: true centres and attitudes plus Gaussian noise of the set's std_xy (per horizontal
    axis), std_z and std_att (degrees, per rotation axis, in the camera frame)."""
    records = []
    for v in views:
        n = conf[v.image_set]
        C = v.C + rng.normal(0.0, 1.0, 3) * [n["std_xy"], n["std_xy"], n["std_z"]]
        R = v.R @ small_rotation(rng, n["std_att"])
        lat, lon, h = frame.to_wgs84(C[None])
        records.append(
            PosRecord(
                v.name, float(lat[0]), float(lon[0]), float(h[0]), R, n["std_xy"], n["std_z"], n["std_att"]
            )
        )
    return records


def render_views(
    renderer: Renderer,
    views: list[View],
    cams: dict[str, Camera],
    lights: dict[str, np.ndarray],
    conf: dict,
    seed: int,
    ss: int,
    out_dir: Path,
) -> tuple[list[np.ndarray], list[np.ndarray], list[tuple[str, str, float]]]:
    """Render every view (ground first: their sample points are tested against every aerial depth) to
    images/ and gt/depth.h5; (true surface points, their colours, co-visible aerial-ground pairs)."""
    gtc = conf["gt"]
    n_per = max(1, math.ceil(gtc["n_points"] / len(views)))
    ground_pts: dict[str, np.ndarray] = {}
    covis: list[tuple[str, str, float]] = []
    points, colours = [], []
    with h5py.File(out_dir / DEPTH_FILE, "w", track_order=True) as h5:
        for idx, v in enumerate(tqdm(views, desc="synth", unit="img")):
            t1 = time.perf_counter()
            cam = cams[v.image_set]
            lin, depth = renderer(v, cam, lights[v.image_set], ss)
            rgb = develop(lin, conf["lighting"][v.image_set], np.random.default_rng([seed, 1, idx]))
            (out_dir / "images" / v.name).write_bytes(encode_jpeg(rgb, conf["render"]["jpeg_quality"]))
            h5.create_dataset(
                depth_key(v.name), data=depth, compression="gzip", compression_opts=4, shuffle=True,
                track_times=False,
            )  # fmt: skip
            # true surface points for gt/sparse
            ii, jj = np.nonzero((depth > 0) & (depth < gtc["max_point_depth"]))
            if len(ii):
                pick = np.random.default_rng([seed, 2, idx]).choice(
                    len(ii), min(n_per, len(ii)), replace=False
                )
                pick.sort()
                uv = np.stack([jj[pick] + 0.5, ii[pick] + 0.5], 1)
                points.append(v.pose.unproject(cam.K, uv, depth[ii[pick], jj[pick]].astype(np.float64)))
                colours.append(rgb[ii[pick], jj[pick]])
            # co-visibility
            if v.image_set == "ground":
                uv, d = pixel_grid(depth, gtc["covis_step"])
                ground_pts[v.name] = v.pose.unproject(cam.K, uv, d)
            else:
                for g in (w for w in views if w.image_set == "ground"):
                    ov = visible_fraction(ground_pts[g.name], cam, v.pose, depth)
                    if ov >= gtc["covis_min"]:
                        covis.append((v.name, g.name, ov))
            sky = float((depth == 0).mean())
            log.info(
                "%s (%s) rendered in %.1f s, sky %.0f%%", v.name, v.kind, time.perf_counter() - t1, 100 * sky
            )
    return points, colours, covis


def write_truth(
    out_dir: Path,
    conf: dict,
    seed: int,
    ss: int,
    textures_dir: Path | None,
    scene: Scene,
    aerial: list[View],
    ground: list[View],
    cams: dict[str, Camera],
    lights: dict[str, np.ndarray],
    points: list[np.ndarray],
    colours: list[np.ndarray],
    covis: list[tuple[str, str, float]],
    r_pos: np.random.Generator,
) -> np.ndarray:
    """pos.csv (noisy POS), cameras.json, gt/sparse (true poses and surface points), gt/covisible.csv
    and gt/scene.json; the true points (P, 3)."""
    frame = LocalFrame(**conf["origin"])
    all_views = aerial + ground
    write_pos_csv(out_dir / "pos.csv", noisy_pos(all_views, conf["pos"], frame, r_pos))
    write_cameras_json(out_dir / "cameras.json", cams)
    P = np.concatenate(points) if points else np.zeros((0, 3))
    Cl = np.concatenate(colours) if colours else np.zeros((0, 3), np.uint8)
    write_model(out_dir / "gt" / "sparse", cams, {v.name: (v.image_set, v.pose) for v in all_views}, P, Cl)
    write_covisible(out_dir / "gt" / "covisible.csv", covis)
    meta = {
        "preset": conf["name"],
        "seed": seed,
        "supersample": ss,
        "textures": str(textures_dir) if textures_dir is not None else None,
        "conf": conf,
        "origin": conf["origin"],
        "frame": "local ENU (metres, z up), ground plane z = 0",
        "lighting": {
            k: {**conf["lighting"][k], "sun_vector": np.round(lights[k][L_SUN : L_SUN + 3], 6).tolist()}
            for k in cams
        },
        "views": [{"name": v.name, "kind": v.kind, "center": np.round(v.C, 6).tolist()} for v in all_views],
        "counts": {
            "aerial": len(aerial),
            "ground": len(ground),
            "covisible": len(covis),
            "points": len(P),
            "boxes": len(scene.boxes),
            "spheres": len(scene.sph),
        },
        "primitives": scene.to_json(),
    }
    (out_dir / "gt" / "scene.json").write_text(json.dumps(meta, indent=1))
    return P


def main(
    conf: dict,
    out_dir: Path,
    seed: int = 0,
    textures_dir: Path | None = None,
    supersample: int | None = None,
    overwrite: bool = False,
) -> Path:
    """Render the survey of preset `conf` (presets.confs[...]) into out_dir; returns out_dir.

    Same conf, seed and textures -> identical files. Raises FileExistsError when out_dir is not empty
    (unless overwrite), FileNotFoundError when textures_dir does not exist or holds no photos.
    """
    out_dir = Path(out_dir)
    if textures_dir is not None and not list_photos(Path(textures_dir)):
        raise FileNotFoundError(f"texture folder {textures_dir} does not exist or holds no jpg/png photos")
    _prepare(out_dir, overwrite)
    ss = int(supersample or conf["render"]["supersample"])
    if ss < 1:
        raise ValueError(f"supersample must be >= 1, not {ss}")
    with stage("synth", log):
        t0 = time.perf_counter()
        photos, scene, aerial, ground, r_pos = build_survey(conf, seed, textures_dir)
        cams = {"aerial": pinhole(conf["aerial"]), "ground": pinhole(conf["ground"])}
        lights = {k: light_array(conf["lighting"][k]) for k in cams}
        log.info(
            "preset %s seed %d: %d boxes, %d spheres, %d aerial + %d ground images, supersampling %dx%d",
            conf["name"], seed, len(scene.boxes), len(scene.sph), len(aerial), len(ground), ss, ss,
        )  # fmt: skip
        renderer = Renderer(scene, photos, seed, conf["render"]["grid_cell"])
        points, colours, covis = render_views(
            renderer, ground + aerial, cams, lights, conf, seed, ss, out_dir
        )
        P = write_truth(out_dir, conf, seed, ss, textures_dir, scene, aerial, ground, cams, lights, points,
                        colours, covis, r_pos)  # fmt: skip
        log.info(
            "%d aerial + %d ground images, %d co-visible pairs, %d points in %.1f s -> %s",
            len(aerial), len(ground), len(covis), len(P), time.perf_counter() - t0, out_dir,
        )  # fmt: skip
    return out_dir
