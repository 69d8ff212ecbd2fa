"""Matching one rendered intermediate view against its candidate aerial and ground images.

One unit of work per view (`match_view`), independent of every other view, so that the service can fan
it out to workers. The render's features are extracted on the fly (a render is seen once); the aerial
and ground images' features come from the shared cache (services.matching.features), which `prepare_features`
fills once before the fan-out (workers only read it). Each pair render <-> image is matched
(LightGlue by default) and verified by a fundamental-matrix RANSAC (services.matching.direct).

Output: matches/VIEW.h5 in the common match file format, with the render as image `views/VIEW.png`
(set "views"), the aerial and ground images with their cached keypoints, and the pairs
(render, aerial) and (render, ground) with their putative matches, scores and RANSAC inliers. The file
carries the view's name (`/views`) and the fingerprint of its inputs (attribute `fingerprint`), so a
rerun with the same inputs is skipped.
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from services.matching import direct
from services.matching import features as features_mod
from shared.matchfile import MatchFile, PairMatches

logger = logging.getLogger("midview.matching.views")

confs: dict[str, dict[str, Any]] = {
    "aliked-lightglue": {
        "name": "views-aliked-lightglue",
        "features": "aliked",
        "max_keypoints": None,  # None: the feature conf's; else overrides it for renders and images
        "render_max_keypoints": None,  # None: max_keypoints; else the renders' own keypoint budget
        "render_detection_threshold": None,  # None: the extractor's; ALIKED: -1 keeps the top-k always
        "resize_max": None,  # None: the feature conf's
        # filter_threshold: LightGlue's (its default), the score a match needs to be kept
        "matcher": {"name": "lightglue", "features": "aliked", "filter_threshold": 0.1},
        "ransac": dict(direct.RANSAC),
        "min_depth_fraction": 0.0,  # skip renders with less valid depth than this (0: never)
    },
    "sift": {
        "name": "views-sift",
        "features": "sift",
        "max_keypoints": None,
        "render_max_keypoints": None,  # (no render_detection_threshold: SIFT has none to set)
        "resize_max": None,
        "matcher": {"name": "nn-ratio", "ratio": 0.8, "mutual": True},
        "ransac": dict(direct.RANSAC),
        "min_depth_fraction": 0.0,
    },
}

VIEW_SET = "views"


def view_image_name(view_name: str) -> str:
    """The name of a render in match files: views/NAME.png."""
    return f"{VIEW_SET}/{view_name}.png"


def feature_conf(conf: dict[str, Any]) -> dict[str, Any]:
    """The feature conf of a matching conf, with its keypoint and size overrides (own cache name)."""
    f = conf["features"]
    fconf = json.loads(json.dumps(features_mod.confs[f] if isinstance(f, str) else f))
    tags = []
    if conf.get("max_keypoints"):
        key = "max_num_keypoints" if fconf["model"]["name"] == "aliked" else "max_num_features"
        fconf["model"][key] = int(conf["max_keypoints"])
        tags.append(f"k{int(conf['max_keypoints'])}")
    if conf.get("resize_max"):
        fconf["preprocessing"]["resize_max"] = int(conf["resize_max"])
        tags.append(f"r{int(conf['resize_max'])}")
    if tags:
        fconf["output"] = fconf["output"] + "-" + "-".join(tags)
    return fconf


def render_feature_conf(conf: dict[str, Any]) -> dict[str, Any]:
    """The feature conf of the renders: the images' with the render_* entries of conf applied."""
    fconf = feature_conf(
        {**conf, "max_keypoints": conf.get("render_max_keypoints") or conf.get("max_keypoints")}
    )
    if conf.get("render_detection_threshold") is not None:
        if fconf["model"]["name"] != "aliked":
            raise ValueError("render_detection_threshold applies to ALIKED only")
        fconf["model"]["detection_threshold"] = float(conf["render_detection_threshold"])
    return fconf


def prepare_features(
    conf: dict[str, Any], image_dir: str | Path, names: list[str], feature_path: str | Path
) -> Path:
    """Extract (cached) features of the aerial and ground images the views will be matched with."""
    return features_mod.main(feature_conf(conf), image_dir, sorted(set(names)), feature_path)


def _fingerprint(conf: dict, view: dict, render_path: Path, image_dir: Path, feature_path: Path) -> str:
    h = hashlib.sha256()
    h.update(json.dumps(conf, sort_keys=True).encode())
    h.update(
        json.dumps(
            {k: view.get(k) for k in ("name", "camera", "pose", "aerial", "ground")}, sort_keys=True
        ).encode()
    )
    h.update(hashlib.sha256(render_path.read_bytes()).digest())  # the render's content
    with features_mod.image_digests(feature_path) as dg:  # the images (their cached features)
        for name in (*view.get("aerial", []), *view.get("ground", [])):
            p = image_dir / name
            h.update(f"{name}:{dg.digest(p) if p.exists() else -1}".encode())
    return h.hexdigest()[:32]


def _read_fingerprint(path: Path) -> str | None:
    try:
        with h5py.File(path, "r") as f:
            v = f.attrs.get("fingerprint")
            return None if v is None else str(v)
    except OSError:
        return None


def _image_features(fconf: dict, feature_path: Path, image_dir: Path, name: str) -> dict[str, np.ndarray]:
    """Cached features of an image; extracted in memory (not cached) when the cache lacks it."""
    try:
        return features_mod.load_features(feature_path, name)
    except (KeyError, OSError):
        from shared.images import read_image

        logger.warning(
            "%s is not in the feature cache %s: extracting it for this view only", name, feature_path
        )
        img = read_image(image_dir / name, grayscale=fconf["preprocessing"].get("grayscale", False))
        f = features_mod.extract(fconf, img)
        f["image_size"] = np.array([img.shape[1], img.shape[0]], np.int64)
        return f


def match_view(
    conf: dict[str, Any],
    view: dict,
    views_dir: str | Path,
    image_dir: str | Path,
    feature_path: str | Path,
    out_dir: str | Path,
    overwrite: bool = False,
) -> Path:
    """Match one rendered view (an entry of views/views.json) against its candidate aerial and ground
    images; write and return out_dir/NAME.h5 (skipped when it exists with the same input fingerprint)."""
    from shared.images import read_image

    conf = {**confs["aliked-lightglue"], **conf}
    views_dir, image_dir = Path(views_dir), Path(image_dir)
    feature_path, out_dir = Path(feature_path), Path(out_dir)
    name = view["name"]
    render_path = views_dir / view.get("image", f"{name}.png")
    out = out_dir / f"{name}.h5"
    fp = _fingerprint(conf, view, render_path, image_dir, feature_path)
    if not overwrite and out.is_file() and _read_fingerprint(out) == fp:
        logger.debug("%s: up to date", out)
        return out
    fconf = feature_conf(conf)
    rconf = render_feature_conf(conf)
    t0 = time.perf_counter()
    image = read_image(render_path, grayscale=rconf["preprocessing"].get("grayscale", False))
    fr = features_mod.extract(rconf, image)
    fr["image_size"] = np.array([image.shape[1], image.shape[0]], np.int64)
    t_extract = time.perf_counter() - t0
    rname = view_image_name(name)
    others = list(dict.fromkeys([*view.get("aerial", []), *view.get("ground", [])]))
    stats = {"extract_s": round(t_extract, 3), "pairs": {}}
    tmp = out.with_suffix(".h5.tmp")
    with MatchFile(tmp, "w", method=conf.get("name", "views")) as mf:
        mf.add_keypoints(rname, fr["keypoints"], tuple(int(v) for v in fr["image_size"]), fr["scores"])
        vidx = mf.view_index(name)
        for other in others:
            fo = _image_features(fconf, feature_path, image_dir, other)
            mf.add_keypoints(other, fo["keypoints"], tuple(int(v) for v in fo["image_size"]), fo["scores"])
            t1 = time.perf_counter()
            pm = direct.match_pair(conf, rname, other, fr, fo)
            pm.views = np.full(len(pm.matches), vidx, np.int32)
            mf.add_pair(pm)
            stats["pairs"][other] = {
                "nim": int(len(pm.matches)),
                "ncm": int(pm.inliers.sum()),
                "seconds": round(time.perf_counter() - t1, 3),
            }
        mf.h5.attrs["view"] = name
        mf.h5.attrs["stats"] = json.dumps(stats)
        mf.h5.attrs["fingerprint"] = fp
    tmp.replace(out)
    logger.info(
        "%s: %d keypoints, %d pairs, inliers %s in %.1f s",
        name,
        len(fr["keypoints"]),
        len(others),
        [s["ncm"] for s in stats["pairs"].values()],
        time.perf_counter() - t0,
    )
    return out


def read_view_matches(path: str | Path) -> tuple[str, dict[str, np.ndarray], list[PairMatches], dict]:
    """(view name, keypoints per image name, pairs, stats) of a matches/VIEW.h5."""
    with MatchFile(path, "r") as mf:
        view = str(mf.h5.attrs.get("view", Path(path).stem))
        kps = {n: mf.keypoints(n) for n in mf.image_names()}
        pairs = list(mf.iter_pairs())
        stats = json.loads(mf.h5.attrs.get("stats", "{}"))
    return view, kps, pairs, stats


def main(
    conf: dict[str, Any],
    views_json: str | Path,
    image_dir: str | Path,
    feature_path: str | Path,
    out_dir: str | Path,
    progress=None,
) -> list[Path]:
    """Match every rendered view of views_json (in order), one `match_view` each."""
    views_json = Path(views_json)
    doc = json.loads(views_json.read_text())
    names = sorted({n for v in doc["views"] for n in (*v.get("aerial", []), *v.get("ground", []))})
    prepare_features(conf, image_dir, names, feature_path)
    outs = []
    for i, v in enumerate(doc["views"]):
        outs.append(match_view(conf, v, views_json.parent, image_dir, feature_path, out_dir))
        if progress is not None:
            progress((i + 1) / len(doc["views"]), v["name"])
    return outs
