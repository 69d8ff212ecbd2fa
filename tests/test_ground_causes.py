"""Every ground image left out says why, in one of a few named causes (services.sfm.combined.report),
from what the reducer (services.reduce.reducer.view_cover) and the combined SfM recorded of it."""

from __future__ import annotations

from services.reduce.reducer import view_cover
from services.sfm.combined.report import CAUSES, cause_of


def test_view_cover_counts_the_views_a_ground_image_is_a_candidate_of():
    doc = {
        "views": [
            {"name": "V1", "ground": ["ground/G1.jpg"], "render": {"source_fraction": 0.04}},
            {"name": "V2", "ground": ["ground/G1.jpg", "ground/G2.jpg"], "render": {"source_fraction": 0.6}},
            {"name": "V3", "ground": ["ground/G3.jpg"], "render": {"source_fraction": 0.02}},
        ]
    }
    cover = view_cover(doc)
    assert cover["ground/G1.jpg"] == {"views": 2, "view_aerial_fraction": 0.6}
    assert cover["ground/G3.jpg"] == {"views": 1, "view_aerial_fraction": 0.02}
    assert "ground/G4.jpg" not in cover


def test_each_image_left_out_gets_the_first_cause_that_holds():
    reg = {"ground/R.jpg"}
    nothing = {"views": 2, "view_aerial_fraction": 0.5, "num_correspondences": 80, "num_inliers": 3}
    assert cause_of("g", {"dropped": True}, nothing, [], reg) == "ambiguous"
    assert cause_of("g", {}, {**nothing, "accepted": True}, [], reg) == "ambiguous"
    assert cause_of("g", {}, {**nothing, "num_inliers": 40}, [], reg) == "ties-without-pose"
    assert cause_of("g", {}, nothing, ["ground/R.jpg"], reg) == "ties-without-pose"
    assert cause_of("g", {}, nothing, ["ground/U.jpg"], reg) == "chained-to-unregistered"
    assert cause_of("g", {}, {**nothing, "view_aerial_fraction": 0.03}, [], reg) == "no-aerial-view"
    assert cause_of("g", {}, {**nothing, "views": 0}, [], reg) == "no-aerial-view"
    assert cause_of("g", {}, nothing, [], reg) == "views-without-ties"
    assert set(CAUSES) == {
        "no-aerial-view", "views-without-ties", "ties-without-pose", "chained-to-unregistered", "ambiguous"
    }  # fmt: skip
