"""bench/ground_report.py: each ground image's cause (in or out, and why) from a job's reports."""

import pytest
from test_bench_splat_views import load_bench


@pytest.fixture(scope="module")
def bench():
    return load_bench("ground_report")


def test_ground_ground_pairs_count_only_verified_pairs_and_registered_partners(bench):
    report = {
        "ground_pairs": {
            "ground/G1.jpg ground/G2.jpg": {"accepted": True, "inliers": 329},
            "ground/G1.jpg ground/G3.jpg": {"accepted": False, "inliers": 100},
            "ground/G2.jpg ground/G4.jpg": {"accepted": True, "inliers": 12},
        }
    }
    gg = bench.ground_ground(report, {"ground/G3.jpg", "ground/G4.jpg"}, 15)
    assert gg["ground/G1.jpg"] == {"largest_pair": 329, "registered_partners": 0}
    # G2-G4 is verified but below 15 matches: its largest pair, not a registered partner
    assert gg["ground/G2.jpg"] == {"largest_pair": 329, "registered_partners": 0}
    assert gg["ground/G4.jpg"] == {"largest_pair": 12, "registered_partners": 0}
    assert gg["ground/G3.jpg"]["largest_pair"] == 0  # its one pair was rejected
    gg = bench.ground_ground(report, {"ground/G2.jpg"}, 15)
    assert gg["ground/G1.jpg"]["registered_partners"] == 1


@pytest.mark.parametrize(
    "row, expected",
    [
        ({"registered": True, "error_m": 0.3, "reason": None, "largest_pair": 0}, "within"),
        ({"registered": True, "error_m": 0.7, "reason": None, "largest_pair": 300}, "off"),
        ({"registered": True, "error_m": None, "reason": None, "largest_pair": 300}, "off"),
        (
            {
                "registered": False,
                "error_m": None,
                "reason": "registered by the mapper but dropped: position ill-determined (std 3.53 m)",
                "largest_pair": 329,
            },
            "dropped",
        ),
        ({"registered": False, "error_m": None, "reason": "pairs", "largest_pair": 479}, "ground-only"),
        ({"registered": False, "error_m": None, "reason": "no pair", "largest_pair": 14}, "unmatched"),
    ],
)
def test_each_image_gets_one_cause(bench, row, expected):
    assert bench.cause(row, 0.5, 15) == expected


def test_summary_counts_every_cause_and_names_the_images(bench):
    rows = [
        {"name": "ground/G1.jpg", "cause": "within"},
        {"name": "ground/G2.jpg", "cause": "ground-only"},
        {"name": "ground/G3.jpg", "cause": "ground-only"},
    ]
    s = bench.summary(rows)
    assert s["counts"] == {"within": 1, "off": 0, "dropped": 0, "ground-only": 2, "unmatched": 0}
    assert s["images"] == {"within": ["ground/G1.jpg"], "ground-only": ["ground/G2.jpg", "ground/G3.jpg"]}


@pytest.mark.parametrize(
    "reason, kind",
    [
        ("an uncalibrated fundamental matrix explains more of its matches than any motion", "calibrated"),
        ("against the aerial surface: its matches fit one pose of the second camera for 68", "surface"),
        ("against the other pairs: its baseline stands 172 deg from where the other pairs", "consistency"),
        ("relative rotation 87.2 deg from the POS (> 14.7); baseline direction 143.2 deg", "pos"),
        ("baseline direction 131.0 deg from the POS (> 58.5)", "pos"),
        ("relative rotation 5.8 deg from the images' aerial-tied attitudes (> 4.0)", "attitudes"),
        (
            "relative rotation 20.1 deg from the POS (> 14.7); relative rotation 21.0 deg from the images'",
            "pos",
        ),
        ("12 inliers (< 15)", "few"),
        (None, "few"),
    ],
)
def test_a_refused_pair_is_put_down_to_the_check_that_refused_it(bench, reason, kind):
    assert bench.refusal_kind(reason) == kind


def test_refusals_are_counted_by_check_as_false_or_mostly_correct(bench):
    pairs = {
        "a b": {"kind": "surface", "inliers": 332, "gt_correct": 308},  # a true pair the check refused
        "a c": {"kind": "surface", "inliers": 79, "gt_correct": 1},  # almost all wrong, but not false
        "b c": {"kind": "calibrated", "inliers": 29, "gt_correct": 0},
        "c d": {"kind": "calibrated", "inliers": 0, "gt_correct": 0},  # not verified even without the check
    }
    by = bench.refusals_by_kind(pairs)
    assert by["surface"] == {"verified_without": 2, "false": 0, "mostly_correct": 1}
    assert by["calibrated"] == {"verified_without": 1, "false": 1, "mostly_correct": 0}
