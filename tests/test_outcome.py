"""A succeeded job's outcome: registered images per set and the warnings a user must see."""

from shared.outcome import job_outcome


def test_outcome_of_a_job_that_registered_no_ground_image():
    m = {
        "aerial_sfm": {"NRI": {"aerial": "10/10"}, "num_points3D": 900},
        "combined_sfm": {
            "num_registered": {"aerial": 10, "ground": 0},
            "num_images": {"aerial": 10, "ground": 4},
            "causes": {"views-without-ties": 3, "ambiguous": 1},
        },
    }
    out = job_outcome(m)
    assert out["result"] == "warnings" and out["registered"] == {"aerial": 10, "ground": 0}
    assert out["warnings"] == ["no ground image registered (0 of 4)"]
    assert out["causes"] == {"views-without-ties": 3, "ambiguous": 1}  # why they were left out


def test_outcome_ok_partial_and_aerial_only():
    full = {
        "combined_sfm": {
            "num_registered": {"aerial": 5, "ground": 3},
            "num_images": {"aerial": 5, "ground": 3},
        }
    }
    assert job_outcome(full) == {**job_outcome(full), "result": "ok", "warnings": []}
    part = {"combined_sfm": {"NRI": {"aerial": "4/5", "ground": "2/3"}}}
    assert job_outcome(part)["warnings"] == [
        "1 of 3 ground images not registered",
        "1 of 5 aerial images not registered",
    ]
    aerial = {"aerial_sfm": {"NRI": {"aerial": "9/10"}}}
    assert job_outcome(aerial)["from_stage"] == "aerial_sfm" and job_outcome(aerial)["result"] == "warnings"
    assert job_outcome({})["result"] == "ok" and job_outcome({})["registered"] == {}
