"""Block-wise 3DGS: crop cameras, block plans that cover every view, resumable block training, the
block renderer and blocks that cannot be trained."""

import json

import numpy as np
import pytest
import torch

from services.colmap_model import Camera, write_model
from services.splat.backend import rasterization
from services.splat.blocks import (
    Block,
    Crop,
    grid_cells,
    merge_blocks,
    plan_blocks,
    read_blocks,
    split_model,
    train_block,
    write_plan,
)
from services.splat.model import create_splats
from services.splat.ply import load_ply, save_ply
from services.splat.render import look_at, render
from services.splat.synthetic import random_scene
from services.views import BlockRenderer

PARAMS = ("means", "quats", "scales", "opacities", "sh")


@pytest.mark.parametrize("backend", ["reference", "cpu"])
@pytest.mark.parametrize(
    "crop", [Crop("a", 10, 8, 42, 40), Crop("a", 0, 13, 29, 48), Crop("a", 37, 0, 64, 21)]
)
def test_a_crop_camera_renders_the_crop_of_the_full_render(backend, crop):
    """Values and gradients of a crop camera's render equal those of the same window of the full render."""
    W, H = 64, 48
    s = random_scene(400, W, H, seed=5, sigma_px=(0.3, 6.0))
    K = s["K"].double().numpy()
    out = {}
    for name, (k, w, h, window, limits) in {
        "full": (K, W, H, (slice(crop.y0, crop.y1), slice(crop.x0, crop.x1)), None),
        "crop": (crop.intrinsics(K), *crop.size, (slice(None), slice(None)), Crop.limits(K, W, H)),
    }.items():
        p = {key: s[key].clone().requires_grad_() for key in PARAMS}
        c, a, _ = rasterization(
            p["means"], p["quats"], p["scales"], p["opacities"], p["sh"], s["viewmat"],
            torch.tensor(k, dtype=torch.float32), w, h, sh_degree=0, render_mode="RGB+ED", backend=backend,
            limits=limits,
        )  # fmt: skip
        c, a = c[window], a[window]
        wts = torch.rand(c.shape, generator=torch.Generator().manual_seed(1))
        ((c * wts).sum() + a.sum()).backward()
        out[name] = (c.detach(), a.detach(), {key: p[key].grad for key in PARAMS})
    (c0, a0, g0), (c1, a1, g1) = out["full"], out["crop"]
    assert c0.shape == c1.shape and a0.abs().sum() > 0
    torch.testing.assert_close(c1, c0, atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(a1, a0, atol=1e-5, rtol=1e-4)
    for key in PARAMS:
        torch.testing.assert_close(g1[key], g0[key], atol=1e-5, rtol=1e-3)


def test_a_downscaled_crop_has_the_scaled_camera():
    crop = Crop("a", 100, 50, 900, 650, scale=0.5)
    K = np.array([[800.0, 0, 500], [0, 800, 400], [0, 0, 1]])
    assert crop.size == (400, 300)
    np.testing.assert_allclose(crop.intrinsics(K), [[400, 0, 200], [0, 400, 175], [0, 0, 1]])


def test_grid_cells_hold_the_samples_in_cells_of_the_given_size():
    rng = np.random.default_rng(0)
    dense = rng.uniform([0, 0, 0], [60, 30, 10], (3000, 3))
    stray = rng.uniform([200, 200, 0], [201, 201, 1], (10, 3))  # under min_share: no cell
    cells = grid_cells(np.concatenate([dense, stray]), 20.0, 0.02)
    assert len(cells) == 6
    for lo, hi in cells:
        np.testing.assert_allclose((hi - lo)[:2], [20.0, 20.0])
        assert lo[2] >= -0.5 and hi[2] <= 10.5 and hi[2] - lo[2] > 8
    every = np.zeros(len(dense), bool)
    for lo, hi in cells:
        every |= ((dense[:, :2] >= lo[:2]) & (dense[:, :2] <= hi[:2])).all(1)
    assert every.all()


# -- a small survey of a textured wall of Gaussians, with an aerial SfM model of it ------------------
WALL_CAM = Camera("PINHOLE", 96, 72, [90.0, 90.0, 48.0, 36.0])


def _wall(n=2500, seed=0):
    """A wall (x in [-6, 6], z in [0, 6] at y = 0) of small opaque Gaussians, painted in 0.75 m squares of
    random colours (a texture the aerial images resolve)."""
    g = np.random.default_rng(seed)
    pts = np.c_[g.uniform(-6, 6, n), np.zeros(n), g.uniform(0, 6, n)]
    palette = g.uniform(0.05, 0.95, (16, 8, 3))
    cols = palette[(pts[:, 0] // 0.75).astype(int) + 8, (pts[:, 2] // 0.75).astype(int)]
    m = create_splats(pts, cols, sh_degree=0, init_opacity=0.95)
    with torch.no_grad():
        m["scales"][:] = float(np.log(0.12))
    return m, pts


@pytest.fixture(scope="module")
def survey(tmp_path_factory):
    """A 'true' wall model, aerial images of it, a COLMAP model with the true points, a blurred
    whole-scene model (the coarse 3DGS) and two planned views near the wall."""
    import cv2

    root = tmp_path_factory.mktemp("blocks")
    truth, pts = _wall()
    aerial = {}
    (root / "images" / "aerial").mkdir(parents=True)
    stations = [(x, y, z) for x in (-4.0, 0.0, 4.0) for y, z in ((-14.0, 9.0), (-11.0, 4.0))]
    for i, (x, y, z) in enumerate(stations):
        pose = look_at(np.array([x, y, z]), np.array([x * 0.5, 0.0, 3.0]))
        name = f"aerial/A{i:04d}.png"
        img = render(truth, WALL_CAM, pose, backend="cpu")["color"]
        cv2.imwrite(str(root / "images" / name), (img[..., ::-1] * 255).round().astype(np.uint8))
        aerial[name] = ("aerial", pose)
    cols = np.full((len(pts), 3), 128, np.uint8)
    write_model(root / "sparse", {"aerial": WALL_CAM}, aerial, pts, cols)
    coarse = {k: v.detach().clone() for k, v in truth.items()}
    coarse["scales"] += float(np.log(2.5))  # smeared
    save_ply(coarse, root / "whole" / "point_cloud.ply")
    views = []
    for i, (x, y) in enumerate(((-3.0, -6.0), (3.0, -6.0))):
        pose = look_at(np.array([x, y, 2.0]), np.array([x, 0.0, 2.5]))
        views.append(
            {
                "name": f"view{i}",
                "camera": WALL_CAM.__dict__,
                "pose": {"R": pose.R.tolist(), "t": pose.t.tolist()},
            }
        )
    return {"root": root, "truth": truth, "views": views}


def _plan(survey, **conf):
    import pycolmap

    root = survey["root"]
    model = load_ply(root / "whole" / "point_cloud.ply")
    conf = {"block_px": 40, "max_crop_px": 64, "min_crop_px": 8, **conf}
    strategy = {"refine_start_iter": 2, "refine_stop_iter": 10, "refine_every": 3, "grow_grad2d": 1e-7}
    conf["train"] = {"steps": 12, "ckpt_every": 4, "strategy": strategy}
    plan = plan_blocks(conf, model, pycolmap.Reconstruction(str(root / "sparse")), survey["views"], "cpu")
    return write_plan(plan, root / "blocks" / "plan.json")


def test_every_planned_view_is_covered_by_a_block_with_crops(survey):
    path = _plan(survey)
    plan = json.loads(path.read_text())
    blocks = read_blocks(path)
    assert {v for b in blocks for v in b.views} == {"view0", "view1"} and plan["uncovered"] == []
    assert len(blocks) >= 2  # 12 m of wall, cells of 40 px of ~0.15 m
    for b in blocks:
        assert b.reason is None and b.crops
        for c in b.crops:
            assert 0 <= c.x0 < c.x1 <= WALL_CAM.width and 0 <= c.y0 < c.y1 <= WALL_CAM.height
            assert max(c.size) <= 64


def test_a_block_killed_mid_training_resumes_to_the_same_result(survey, tmp_path, monkeypatch):
    from services.splat import train

    path = _plan(survey)
    root = survey["root"]
    args = (root / "whole" / "point_cloud.ply", root / "sparse", root / "images")
    a = train_block(path, "b00", *args, tmp_path / "a", backend="cpu")
    assert a["trained"] and a["steps"] == 12 and a["gaussians"] > a["gaussians_before"] > 0
    real = train.Trainer.train

    def killed(self, resume=False, stop_after=None, progress=True):
        real(self, resume=resume, stop_after=min(stop_after, 6), progress=progress)
        if self.step >= 6:
            raise KeyboardInterrupt

    monkeypatch.setattr(train.Trainer, "train", killed)
    with pytest.raises(KeyboardInterrupt):
        train_block(path, "b00", *args, tmp_path / "b", backend="cpu")
    monkeypatch.setattr(train.Trainer, "train", real)
    assert not (tmp_path / "b" / "b00" / "point_cloud.ply").exists()
    b = train_block(path, "b00", *args, tmp_path / "b", backend="cpu")
    pa, pb = (
        load_ply(tmp_path / "a" / "b00" / "point_cloud.ply"),
        load_ply(tmp_path / "b" / "b00" / "point_cloud.ply"),
    )
    for k in pa:
        assert torch.equal(pa[k], pb[k]), k
    assert b["steps"] == 12
    monkeypatch.setattr(train.Trainer, "train", killed)  # done: a rerun trains nothing
    assert train_block(path, "b00", *args, tmp_path / "b", backend="cpu") == b


def test_block_training_sharpens_its_views_and_the_renderer_uses_it(survey, tmp_path):
    """Trained 150 steps on its crops, a block renders its view closer to the truth than the smeared
    whole-scene model (mean colour error 0.14 -> 0.11 and 0.16 -> 0.12 when written)."""
    path = _plan(survey)
    plan = json.loads(path.read_text())
    plan["conf"]["train"]["steps"] = 150
    plan["conf"]["train"]["strategy"]["refine_stop_iter"] = 0
    write_plan(plan, tmp_path / "plan.json")
    root = survey["root"]
    for b in read_blocks(tmp_path / "plan.json"):
        train_block(tmp_path / "plan.json", b.id, root / "whole" / "point_cloud.ply", root / "sparse",
                    root / "images", tmp_path, backend="cpu")  # fmt: skip
    r = BlockRenderer(root / "whole" / "point_cloud.ply", tmp_path, backend="cpu")
    coarse = load_ply(root / "whole" / "point_cloud.ply")
    for v in survey["views"]:
        from services.colmap_model import Pose

        pose = Pose(np.array(v["pose"]["R"]), np.array(v["pose"]["t"]))
        truth = render(survey["truth"], WALL_CAM, pose, backend="cpu")["color"]
        before = render(coarse, WALL_CAM, pose, backend="cpu")["color"]
        rgb, depth = r.render(WALL_CAM, pose)
        err_before = np.abs(before - truth).mean()
        err_after = np.abs(rgb / 255.0 - truth).mean()
        assert err_after < 0.85 * err_before, (err_before, err_after)
        assert (depth > 0).mean() > 0.5
    merged, ids = merge_blocks(coarse, tmp_path)
    assert sorted(ids) == sorted(b.id for b in read_blocks(tmp_path / "plan.json"))
    assert len(r.model["means"]) == len(merged["means"])


def test_a_block_no_aerial_image_sees_ends_with_a_reason(survey, tmp_path):
    path = _plan(survey, min_visible=1.01)  # no image qualifies
    blocks = read_blocks(path)
    assert all(b.reason == "no aerial image sees this block" for b in blocks)
    root = survey["root"]
    doc = train_block(
        path, blocks[0].id, root / "whole" / "point_cloud.ply", root / "sparse", root / "images", tmp_path
    )
    assert doc == {
        "id": blocks[0].id,
        "trained": False,
        "reason": "no aerial image sees this block",
        "views": blocks[0].views,
    }
    r = BlockRenderer(root / "whole" / "point_cloud.ply", path.parent, backend="cpu")
    assert r.merged == []  # views render from the whole-scene model
    whole = load_ply(root / "whole" / "point_cloud.ply")
    assert all(torch.equal(r.model[k], whole[k].detach()) for k in whole)


def test_split_model_partitions_the_gaussians():
    m, _ = _wall(100)
    b = Block("b00", [-2.0, -1.0, 0.0], [2.0, 1.0, 6.0], ["v"], margin=1.0)
    own, rest = split_model(m, b)
    assert len(own["means"]) + len(rest["means"]) == 100 and len(own["means"]) > 10
    assert bool(b.inside(own["means"]).all()) and not bool(b.inside(rest["means"]).any())
    grown, _ = split_model(m, b, b.margin)
    assert len(grown["means"]) > len(own["means"])


def test_a_block_without_gaussians_ends_with_a_reason(survey, tmp_path):
    """A cell the whole-scene model holds no Gaussian of (densification grows only from Gaussians): not
    trained, with the reason, and not retried on a rerun."""
    plan = json.loads(_plan(survey).read_text())
    b = plan["blocks"][0]
    b["lo"], b["hi"], b["margin"] = [50.0, 50.0, 0.0], [60.0, 60.0, 5.0], 0.0
    path = write_plan(plan, tmp_path / "plan.json")
    root = survey["root"]
    args = (path, b["id"], root / "whole" / "point_cloud.ply", root / "sparse", root / "images", tmp_path)
    doc = train_block(*args, backend="cpu")
    assert not doc["trained"] and doc["reason"] == "the whole-scene 3DGS has no Gaussian in this block"
    assert train_block(*args, backend="cpu") == doc
    r = BlockRenderer(root / "whole" / "point_cloud.ply", tmp_path, backend="cpu")
    assert b["id"] not in r.merged
