"""The common match file (HDF5), written by every matcher and read by evaluation and SfM.

Layout and conventions: docs/formats.md, section "Match file".
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

FORMAT = "midview-matches"
VERSION = 1


def _key(name: str) -> str:
    return name.replace("/", "|")


def pair_key(name0: str, name1: str) -> str:
    return f"{_key(name0)}__{_key(name1)}"


@dataclass
class PairMatches:
    """Matches of one image pair. `matches` (M, 2) int32 indexes keypoints of name0 and name1."""

    name0: str
    name1: str
    matches: np.ndarray
    scores: np.ndarray
    inliers: np.ndarray | None = None
    views: np.ndarray | None = None

    def swapped(self) -> PairMatches:
        return PairMatches(
            self.name1, self.name0, self.matches[:, ::-1].copy(), self.scores, self.inliers, self.views
        )


class MatchFile:
    """Read/write access to a match file. Use as a context manager.

    >>> with MatchFile(path, "w", method="sift") as mf:
    ...     mf.add_keypoints("aerial/A.jpg", kpts, (w, h))
    ...     mf.add_pair(PairMatches("aerial/A.jpg", "ground/G.jpg", m, s))
    """

    def __init__(self, path: str | Path, mode: str = "r", method: str = ""):
        self.path = Path(path)
        if mode in ("w", "a"):
            self.path.parent.mkdir(parents=True, exist_ok=True)
        self.h5 = h5py.File(self.path, mode)
        if mode == "w":
            self.h5.attrs.update(format=FORMAT, version=VERSION, method=method)
            self.h5.create_group("images")
            self.h5.create_group("pairs")
        elif self.h5.attrs.get("format") != FORMAT:
            self.h5.close()
            raise ValueError(f"{self.path}: not a midview match file (format attribute missing)")
        self._views: list[str] = [v.decode() for v in self.h5["views"][()]] if "views" in self.h5 else []

    def __enter__(self) -> MatchFile:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        if self.h5.id.valid:
            if self.h5.mode != "r" and self._views:
                if "views" in self.h5:
                    del self.h5["views"]
                self.h5.create_dataset("views", data=np.array(self._views, dtype=h5py.string_dtype()))
            self.h5.close()

    @property
    def method(self) -> str:
        return str(self.h5.attrs.get("method", ""))

    # -- keypoints -----------------------------------------------------------------------------
    def add_keypoints(
        self, name: str, keypoints: np.ndarray, size: tuple[int, int], scores: np.ndarray | None = None
    ) -> None:
        """Store keypoints (N, 2) in COLMAP pixel convention for an image of size (width, height)."""
        grp = self.h5["images"].require_group(_key(name))
        for ds in ("keypoints", "scores"):
            if ds in grp:
                del grp[ds]
        grp.attrs.update(name=name, width=int(size[0]), height=int(size[1]))
        grp.create_dataset("keypoints", data=np.asarray(keypoints, np.float32).reshape(-1, 2))
        if scores is not None:
            grp.create_dataset("scores", data=np.asarray(scores, np.float32))

    def image_names(self) -> list[str]:
        return sorted(g.attrs["name"] for g in self.h5["images"].values())

    def keypoints(self, name: str) -> np.ndarray:
        return self.h5["images"][_key(name)]["keypoints"][()]

    def image_size(self, name: str) -> tuple[int, int]:
        a = self.h5["images"][_key(name)].attrs
        return int(a["width"]), int(a["height"])

    # -- pairs ---------------------------------------------------------------------------------
    def view_index(self, view: str) -> int:
        if view not in self._views:
            self._views.append(view)
        return self._views.index(view)

    @property
    def views(self) -> list[str]:
        return list(self._views)

    def add_pair(self, pm: PairMatches) -> None:
        for name in (pm.name0, pm.name1):
            if _key(name) not in self.h5["images"]:
                raise KeyError(f"add keypoints of {name} before its matches")
        pk = pair_key(pm.name0, pm.name1)
        if pk in self.h5["pairs"]:
            del self.h5["pairs"][pk]
        grp = self.h5["pairs"].create_group(pk)
        grp.attrs.update(name0=pm.name0, name1=pm.name1)
        m = np.asarray(pm.matches, np.int32).reshape(-1, 2)
        grp.create_dataset("matches", data=m)
        grp.create_dataset("scores", data=np.asarray(pm.scores, np.float32).reshape(-1))
        if pm.inliers is not None:
            grp.create_dataset("inliers", data=np.asarray(pm.inliers, bool).reshape(-1))
        if pm.views is not None:
            grp.create_dataset("views", data=np.asarray(pm.views, np.int32).reshape(-1))

    def pairs(self) -> list[tuple[str, str]]:
        return sorted((g.attrs["name0"], g.attrs["name1"]) for g in self.h5["pairs"].values())

    def get_pair(self, name0: str, name1: str) -> PairMatches | None:
        """Matches of (name0, name1) in that orientation, whichever way they were stored."""
        for a, b, swap in ((name0, name1, False), (name1, name0, True)):
            pk = pair_key(a, b)
            if pk in self.h5["pairs"]:
                g = self.h5["pairs"][pk]
                pm = PairMatches(
                    a,
                    b,
                    g["matches"][()],
                    g["scores"][()],
                    g["inliers"][()] if "inliers" in g else None,
                    g["views"][()] if "views" in g else None,
                )
                return pm.swapped() if swap else pm
        return None

    def iter_pairs(self) -> Iterator[PairMatches]:
        for n0, n1 in self.pairs():
            pm = self.get_pair(n0, n1)
            assert pm is not None
            yield pm
