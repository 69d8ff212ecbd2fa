"""Local features (SIFT, ALIKED), extracted once per image into an HDF5 cache.

Keypoints are stored at the full resolution of the image file in the COLMAP pixel convention
(centre of the top-left pixel at (0.5, 0.5), docs/formats.md). Cache layout, one file per conf:

```
/ (attrs: conf=JSON of the feature conf)
/<image name>/            attrs: width, height, source_size, source_sha256 (of the image file)
/<image name>/keypoints   float32 (N, 2)
/<image name>/descriptors float16 or float32 (N, D)
/<image name>/scores      float32 (N,)
/<image name>/scales, oris  float32 (N,), SIFT only (full-resolution pixels, radians)
```
Re-running skips images already present (same file size and modification time).
"""

from __future__ import annotations

import json
import logging
import time
import warnings
from functools import lru_cache
from pathlib import Path
from typing import Any

import cv2
import h5py
import numpy as np
from tqdm import tqdm

from services.digests import DigestCache
from shared.images import list_images, read_image
from shared.logging import stage

logger = logging.getLogger("midview.features")

confs: dict[str, dict[str, Any]] = {
    "sift": {
        "output": "feats-sift-r1600",
        "model": {"name": "sift", "max_num_features": 8192},
        "preprocessing": {"grayscale": True, "resize_max": 1600},
        "as_half": True,
    },
    "aliked": {
        "output": "feats-aliked-n16-r1024",
        "model": {"name": "aliked", "model_name": "aliked-n16", "max_num_keypoints": 2048},
        "preprocessing": {"grayscale": False, "resize_max": 1024},
        "as_half": True,
    },
}


# -- runtime -----------------------------------------------------------------------------------
def configure_torch() -> str:
    """Apply settings.num_threads to torch; return the torch device of settings.device."""
    import torch

    from shared.config import get_settings

    s = get_settings()
    if s.num_threads > 0 and torch.get_num_threads() != s.num_threads:
        torch.set_num_threads(s.num_threads)
    if s.device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    return s.device


@lru_cache(maxsize=4)
def _load_model(model_json: str, device: str) -> Any:
    """Build (once per process) the extractor described by a model conf."""
    mconf = json.loads(model_json)
    name = mconf.pop("name")
    if name == "sift":
        import pycolmap

        from shared.config import get_settings

        opts = pycolmap.FeatureExtractionOptions()
        opts.num_threads = get_settings().num_threads or -1
        opts.sift.max_num_features = int(mconf.get("max_num_features", 8192))
        for k, v in mconf.items():
            if k != "max_num_features":
                setattr(opts.sift, k, v)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)
            return pycolmap.Sift(opts, pycolmap.Device.cpu)
    if name == "aliked":
        from services.matching.aliked import FastALIKED

        return FastALIKED(**mconf).eval().to(device)
    raise ValueError(f"unknown feature model {name!r}")


def resize_max(image: np.ndarray, max_side: int | None) -> tuple[np.ndarray, np.ndarray]:
    """Downscale so that the long side is <= max_side (never upscale). Returns (image, (sx, sy))
    with sx = full width / resized width: multiply COLMAP-convention coordinates by it."""
    h, w = image.shape[:2]
    if not max_side or max(h, w) <= max_side:
        return image, np.ones(2)
    s = max_side / max(h, w)
    wn, hn = max(1, round(w * s)), max(1, round(h * s))
    out = cv2.resize(image, (wn, hn), interpolation=cv2.INTER_AREA)
    return out, np.array([w / wn, h / hn])


def _extract_sift(model: Any, image: np.ndarray) -> dict[str, np.ndarray]:
    kp, desc = model.extract(np.ascontiguousarray(image))
    kp = np.asarray(kp, np.float32).reshape(-1, 4)
    return {
        "keypoints": kp[:, :2],  # pycolmap: already COLMAP convention
        "scales": kp[:, 2],
        "oris": kp[:, 3],
        "descriptors": np.asarray(desc, np.float32),
        "scores": np.ones(len(kp), np.float32),  # COLMAP's SIFT gives no detection score
    }


def _extract_aliked(model: Any, image: np.ndarray, device: str) -> dict[str, np.ndarray]:
    import torch

    t = torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1)[None].float().div(255.0)
    with torch.inference_mode():
        out = model({"image": t.to(device)})
    return {
        # ALIKED: pixel centres at integer coordinates -> COLMAP convention
        "keypoints": out["keypoints"][0].cpu().numpy().astype(np.float32) + 0.5,
        "descriptors": out["descriptors"][0].cpu().numpy().astype(np.float32),
        "scores": out["keypoint_scores"][0].cpu().numpy().astype(np.float32),
    }


def extract(conf: dict[str, Any], image: np.ndarray) -> dict[str, np.ndarray]:
    """Features of one decoded image (RGB or grayscale uint8), keypoints at full resolution."""
    device = configure_torch()
    pre = conf["preprocessing"]
    if pre.get("grayscale") and image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    elif not pre.get("grayscale") and image.ndim == 2:
        image = cv2.cvtColor(image, cv2.COLOR_GRAY2RGB)
    small, scale = resize_max(image, pre.get("resize_max"))
    name = conf["model"]["name"]
    model = _load_model(json.dumps(conf["model"], sort_keys=True), device if name != "sift" else "cpu")
    feats = _extract_sift(model, small) if name == "sift" else _extract_aliked(model, small, device)
    feats["keypoints"] = (feats["keypoints"] * scale[None]).astype(np.float32)
    if "scales" in feats:
        feats["scales"] = (feats["scales"] * float(scale.mean())).astype(np.float32)
    return feats


# -- cache -------------------------------------------------------------------------------------
def _conf_json(conf: dict[str, Any]) -> str:
    return json.dumps(conf, sort_keys=True)


def _stamp(path: Path, digests: DigestCache) -> tuple[int, str]:
    """(size, sha256) of an image: what its cached features were extracted from."""
    return int(path.stat().st_size), digests.digest(path)


def image_digests(feature_path: Path) -> DigestCache:
    """The images' content digests, cached beside the feature file."""
    return DigestCache(feature_path.parent / f".{feature_path.stem}.digests.json")


def _is_cached(h5: h5py.File, name: str, stamp: tuple[int, str]) -> bool:
    if name not in h5 or not isinstance(h5[name], h5py.Group):
        return False
    g = h5[name]
    complete = all(k in g for k in ("keypoints", "descriptors", "scores"))
    same = (int(g.attrs.get("source_size", -1)), str(g.attrs.get("source_sha256", ""))) == stamp
    return complete and same


def _write(h5: h5py.File, name: str, feats: dict[str, np.ndarray], size, stamp, as_half: bool) -> None:
    if name in h5:
        del h5[name]
    g = h5.create_group(name)
    for k, v in feats.items():
        if k == "descriptors" and as_half:
            v = v.astype(np.float16)
        g.create_dataset(k, data=v)
    # attrs last: a group without them is seen as incomplete and re-extracted
    g.attrs.update(width=int(size[0]), height=int(size[1]), source_size=stamp[0], source_sha256=stamp[1])


def _open_cache(conf: dict[str, Any], feature_path: Path) -> h5py.File:
    """Open the cache for appending; start afresh when it was written with another conf."""
    feature_path.parent.mkdir(parents=True, exist_ok=True)
    h5 = h5py.File(feature_path, "a")
    old = h5.attrs.get("conf")
    if old is not None and old != _conf_json(conf):
        logger.warning("%s was written with another feature conf: extracting again", feature_path)
        h5.close()
        feature_path.unlink()
        h5 = h5py.File(feature_path, "a")
    h5.attrs["conf"] = _conf_json(conf)
    return h5


def _all_cached(conf: dict[str, Any], feature_path: Path, image_dir: Path, names: list[str]) -> bool:
    """Whether every image is in the cache, extracted with this conf from the same file."""
    if not feature_path.is_file():
        return False
    with h5py.File(feature_path, "r") as h5:
        if h5.attrs.get("conf") != _conf_json(conf):
            return False
        paths = {n: image_dir / n for n in names}
        with image_digests(feature_path) as dg:
            return all(p.is_file() and _is_cached(h5, n, _stamp(p, dg)) for n, p in paths.items())


def main(
    conf: dict[str, Any],
    image_dir: str | Path,
    names: list[str] | None = None,
    feature_path: str | Path | None = None,
    overwrite: bool = False,
) -> Path:
    """Extract features of `names` (default: every image under image_dir) into `feature_path`
    (default: image_dir/../features/<conf output>.h5). Cached images are skipped."""
    image_dir = Path(image_dir)
    names = list(names) if names is not None else list_images(image_dir)
    feature_path = Path(feature_path or image_dir.parent / "features" / f"{conf['output']}.h5")
    with stage(f"features:{conf['output']}", logger):
        if not overwrite and _all_cached(conf, feature_path, image_dir, names):
            # opening the cache for writing would touch it and make every consumer look out of date
            logger.info("%d images, all cached -> %s", len(set(names)), feature_path)
            return feature_path
        h5 = _open_cache(conf, feature_path)
        dg = image_digests(feature_path)
        try:
            todo = []
            for n in dict.fromkeys(names):
                path = image_dir / n  # a missing image fails below, in read_image, with a clear error
                if overwrite or not path.is_file() or not _is_cached(h5, n, _stamp(path, dg)):
                    todo.append(n)
            n_all = len(set(names))
            logger.info(
                "%d images, %d cached, %d to extract -> %s", n_all, n_all - len(todo), len(todo), feature_path
            )
            t0 = time.perf_counter()
            for n in tqdm(todo, desc=f"features {conf['output']}", unit="img", disable=not todo):
                image = read_image(image_dir / n, grayscale=conf["preprocessing"].get("grayscale", False))
                feats = extract(conf, image)
                size = (image.shape[1], image.shape[0])
                _write(h5, n, feats, size, _stamp(image_dir / n, dg), conf.get("as_half", True))
                h5.flush()
            if todo:
                dt = time.perf_counter() - t0
                logger.info("extracted %d images in %.1f s (%.2f s/image)", len(todo), dt, dt / len(todo))
        finally:
            h5.close()
            dg.save()
    return feature_path


def load_features(feature_path: str | Path, name: str) -> dict[str, np.ndarray]:
    """Cached features of one image: keypoints, descriptors (float32), scores, image_size (w, h), ..."""
    with h5py.File(feature_path, "r") as h5:
        g = h5[name]
        out = {k: g[k][()] for k in g}
        out["image_size"] = np.array([g.attrs["width"], g.attrs["height"]], np.int64)
    out["descriptors"] = out["descriptors"].astype(np.float32)
    return out
