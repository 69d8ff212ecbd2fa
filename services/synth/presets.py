"""Named configurations of the synthetic survey (`confs[name]`, hloc style)."""

from __future__ import annotations

import copy

ORIGIN = {"lat0": 55.7047, "lon0": 13.1910, "h0": 70.0}  # Lund; ellipsoidal height of the ground plane

# Linear-light radiometry. The aerial flight is flown around noon, the ground walk late in the afternoon
# (lower, warmer sun from the west, different exposure and white balance).
LIGHT_AERIAL = {
    "sun_azimuth": 165.0,  # degrees clockwise from north
    "sun_elevation": 52.0,
    "sun": [1.05, 1.0, 0.92],
    "ambient": [0.26, 0.3, 0.38],
    "zenith": [0.16, 0.3, 0.75],
    "horizon": [0.6, 0.68, 0.8],
    "haze": [0.55, 0.6, 0.68],
    "haze_distance": 2500.0,
    "clouds": 0.3,
    "shadows": True,
    "exposure": 0.95,
    "wb": [1.0, 1.0, 1.0],
    "vignetting": 0.25,
    "read_noise": 1.2,
    "shot_noise": 0.12,
}
LIGHT_GROUND = {
    "sun_azimuth": 250.0,
    "sun_elevation": 24.0,
    "sun": [1.0, 0.8, 0.58],
    "ambient": [0.28, 0.31, 0.4],
    "zenith": [0.2, 0.33, 0.7],
    "horizon": [0.75, 0.72, 0.7],
    "haze": [0.62, 0.6, 0.58],
    "haze_distance": 1500.0,
    "clouds": 0.45,
    "shadows": True,
    "exposure": 1.15,
    "wb": [0.95, 1.0, 1.1],
    "vignetting": 0.15,
    "read_noise": 1.6,
    "shot_noise": 0.2,
}
GROUND_VIEWS = {"along": 0.3, "in": 0.35, "diag": 0.25, "out": 0.1}  # probabilities of the view kinds
POS_NOISE = {
    "aerial": {"std_xy": 0.5, "std_z": 0.8, "std_att": 1.0},  # RTK-less drone GNSS, gimbal IMU
    "ground": {"std_xy": 2.5, "std_z": 4.0, "std_att": 2.0},  # phone GNSS in a street canyon
}

_BASE = {
    "scene": {
        "blocks": [1, 1],  # surveyed blocks (x, y)
        "context": 1,  # rings of unsurveyed blocks around them
        "block": [56.0, 56.0],  # block size including sidewalks (m)
        "road": 12.0,
        "sidewalk": 3.5,
        "lot_min": 10.0,
        "lot_max": 30.0,
        "height": [6.0, 25.0],
        "p_building": 0.8,
        "clutter": 1.0,
    },
    "aerial": {
        "width": 1600,
        "height": 1200,
        "f": 1300.0,
        "altitude": 60.0,
        "overlap": [0.75, 0.75],  # forward, side (nadir camera)
        "grid": [2, 4],  # flight lines x stations; None: cover the surveyed blocks
        "pitch": -45.0,
        "jitter_m": 0.4,
        "jitter_deg": 1.5,
    },
    "ground": {
        "width": 1024,
        "height": 768,
        "f": 750.0,
        "count": 15,
        "height_m": [1.5, 2.5],
        "pitch": [-3.0, 12.0],
        "roll_deg": 1.5,
        "p_lane": 0.7,  # in a driving lane; otherwise on the opposite sidewalk
        "views": GROUND_VIEWS,
    },
    "render": {"supersample": 2, "jpeg_quality": 92, "grid_cell": 4.0, "clearance": 1.5},
    "lighting": {"aerial": LIGHT_AERIAL, "ground": LIGHT_GROUND},
    "pos": POS_NOISE,
    "origin": ORIGIN,
    "gt": {"n_points": 4000, "covis_step": 8, "covis_min": 0.05, "max_point_depth": 300.0},
}


# the `isprs` survey's scene and flight (shared by its presets)
ISPRS_SCENE = {
    "height": [8.0, 20.0],
    "relief": [0.12, 0.3],
    "balconies": 0.35,
    "photo_facades": False,
    "wall_photos": 0.5,
    "transient": 0.33,
}
ISPRS_AERIAL = {"altitude": 50.0, "f": 1400.0, "grid": [3, 4]}


def _preset(name: str, **over: dict) -> dict:
    c = copy.deepcopy(_BASE)
    c["name"] = name
    for k, v in over.items():
        c[k].update(v)
    return c


confs: dict[str, dict] = {
    # unit tests: 2 buildings, 20 aerial (a 2 x 2 grid of stations, a nadir and four obliques each: with
    # one line of two stations the obliques facing away from each other share too little, and the
    # aerial SfM registered 4 of 10 on some machines) + 4 ground images, a few seconds
    "tiny": _preset(
        "tiny",
        scene={
            "context": 0,
            "block": [40.0, 26.0],
            "road": 10.0,
            "sidewalk": 3.0,
            "lot_max": 20.0,
            "height": [8.0, 16.0],
            "p_building": 1.0,
            "clutter": 0.6,
        },
        aerial={
            "width": 480,
            "height": 360,
            "f": 390.0,
            "altitude": 40.0,
            "overlap": [0.6, 0.6],
            "grid": [2, 2],
        },
        ground={
            "width": 320,
            "height": 240,
            "f": 234.0,
            "count": 4,
            "views": {"in": 0.45, "diag": 0.45, "along": 0.1},
        },
        gt={"n_points": 1000},
    ),
    # one block with its neighbours: 40 aerial + 15 ground images, a few minutes on 2 cores
    "small": _preset("small"),
    # `small` walked: 40 ground images 4 m apart in sequence (a walker photographing the facades), the
    # overlapping ground capture of a street survey; 40 aerial + 40 ground images
    "small-walk": _preset(
        "small-walk",
        ground={
            "count": 40,
            "layout": "walk",
            "spacing_m": 4.0,
            "views": {"in": 0.5, "diag": 0.4, "along": 0.1},
        },
    ),
    # modelled on a multi-platform survey like the ISPRS/EuroSDR benchmark's (the seed paper's data): a
    # 5-head oblique flight (nadir and 45-degree obliques) at 50 m, aerial GSD about twice the ground's
    # (3.6 cm nadir, 4-5 cm on the facades; the ground 1-2.5 cm at 7-20 m), facades with depth (openings
    # recessed 12-30 cm behind their reveals, string courses, columns of balconies), half of the walls
    # real brick cut from facade photos (with --textures; the rest procedural render, brick and panels,
    # never whole street photos), sun from the south at noon for the flight and from the west in the
    # afternoon for the ground walk with shadows cast by all, and a third of the parked cars there in
    # one capture only
    "isprs": _preset(
        "isprs",
        scene=ISPRS_SCENE,
        aerial=ISPRS_AERIAL,
        ground={"count": 20},
    ),
    # `isprs` walked: its flight, facades, light and clutter, with 50 ground images 3.5 m apart in sequence
    # around the block (a walker photographing the facades, as mapping teams capture the ground densely)
    "isprs-walk": _preset(
        "isprs-walk",
        scene=ISPRS_SCENE,
        aerial=ISPRS_AERIAL,
        ground={
            "count": 50,
            "layout": "walk",
            "spacing_m": 3.5,
            "views": {"in": 0.5, "diag": 0.4, "along": 0.1},
        },
    ),
    # `isprs` with flat facades: no relief, no balconies, procedural walls, no transient cars; the same
    # flight, ground walk and light (a measurement of what the facades' properties do)
    "isprs-flat": _preset(
        "isprs-flat",
        scene={"height": [8.0, 20.0], "photo_facades": False},
        aerial=ISPRS_AERIAL,
        ground={"count": 20},
    ),
    # 3 x 3 surveyed blocks: ~350 aerial + 150 ground images (long; for a many-core machine)
    "city": _preset(
        "city",
        scene={"blocks": [3, 3], "block": [60.0, 60.0]},
        aerial={"altitude": 70.0, "overlap": [0.7, 0.7], "grid": None},
        ground={"count": 150},
        gt={"n_points": 20000},
    ),
}
