"""Planning the intermediate views (`views.json`): the planners of conf["planner"], then every aerial
image made a candidate of some view, and `main`."""

from __future__ import annotations

import logging
from pathlib import Path

from services.colmap_model import Camera
from services.conf import merge_conf
from services.pos import LocalFrame, PosRecord
from services.sfm import read_georef_frame
from services.views.confs import BASE, confs
from services.views.ground_aware import plan_ground_aware
from services.views.paper import plan_paper, select_paper
from services.views.scene import DepthFn, Scene, load_scene
from services.views.specs import ViewSpec, cover_aerial, summary, write_views
from shared.logging import stage

logger = logging.getLogger("midview.viewpoints")

__all__ = ["NoViews", "confs", "main", "plan"]


def plan(scene: Scene, conf: dict) -> list[ViewSpec]:
    """The views of conf["planner"] (paper, ground-aware or both), sorted by name."""
    n = int(conf["views_per_ground_image"])
    n_paper = int(conf["paper"].get("views_per_ground_image") or n)
    n_ground = int(conf["ground"].get("views_per_ground_image") or n)
    planner = conf["planner"]
    views: list[ViewSpec] = []
    if planner in ("paper", "both"):
        views += select_paper(plan_paper(scene, conf), scene, conf, n_paper)
    if planner in ("ground-aware", "both"):
        views += plan_ground_aware(scene, conf, n_ground)
    if planner not in ("paper", "ground-aware", "both"):
        raise ValueError(f"unknown planner {planner!r} (paper, ground-aware, both)")
    keep_bare = bool(conf["ground"]["keep_without_aerial"])
    views = [v for v in views if v.ground and (v.aerial or (keep_bare and v.planner == "ground-aware"))]
    if conf["candidates"]["cover_aerial"]:
        added = cover_aerial(views, scene, conf["candidates"])
        if added:
            logger.info("%d aerial images added as candidates so that each is covered", added)
    return sorted(views, key=lambda v: v.name)


class NoViews(ValueError):
    """The planner found no view to render."""


def main(
    conf: dict,
    sparse: str | Path,
    pos: str | Path | list[PosRecord],
    cameras: str | Path | dict[str, Camera],
    georef: str | Path | LocalFrame,
    out_path: str | Path,
    depth_fn: DepthFn | None = None,
) -> Path:
    """Plan the intermediate views and write them to `out_path` (views.json). Raises NoViews, writing
    nothing, when no view can be planned."""
    conf = merge_conf(BASE, conf)
    with stage(f"viewpoints:{conf['planner']}", logger):
        scene = load_scene(sparse, pos, cameras, georef, depth_fn, conf)
        views = plan(scene, conf)
        info = summary(views, scene)
        if not views:
            raise NoViews(
                f"no intermediate view could be planned (planner {conf['planner']}, ground images covered "
                f"{info['ground_covered']}): the log's warnings say why for each ground image"
            )
        frame = georef if isinstance(georef, LocalFrame) else read_georef_frame(georef)
        write_views(
            out_path,
            views,
            {
                "planner": conf["planner"],
                "frame": {"type": "ENU", "lat0": frame.lat0, "lon0": frame.lon0, "h0": frame.h0},
                "terrain_z": scene.terrain_z,
                "ground_heights": scene.ground_heights,
                "summary": info,
                "conf": conf,
            },
        )
        logger.info(
            "%d views (%s); ground images covered %s, aerial %s; %d matching pairs -> %s",
            info["num_views"],
            ", ".join(f"{k} {v}" for k, v in info["by_planner"].items()),
            info["ground_covered"],
            info["aerial_covered"],
            info["num_pairs"],
            out_path,
        )
    return Path(out_path)
