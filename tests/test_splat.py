"""3DGS rasterizers: projection, the plain-PyTorch reference (the oracle) and the numba CPU backend."""

import numpy as np
import pytest
import torch

from services.colmap_model import Camera, Pose
from services.splat.backend import rasterization
from services.splat.cpu import rasterize_cpu
from services.splat.model import splats_from_tensors
from services.splat.projection import frustum_candidates, project_gaussians
from services.splat.reference import rasterize_reference
from services.splat.render import look_at, lowered_pose, render
from services.splat.sh import sh_to_rgb
from services.splat.synthetic import random_scene

PARAMS = ("means", "quats", "scales", "opacities", "sh")


def _close(a, b, rel=2e-3):
    """Max abs difference within rel of b's largest magnitude (gradients span orders of magnitude)."""
    a, b = a.double(), b.double()
    return float((a - b).abs().max()) <= rel * max(float(b.abs().max()), 1e-6)


def _projected(n=200, W=64, H=48, seed=0, dtype=torch.float64):
    s = random_scene(n, W, H, seed=seed)
    m2, con, dep, radii = project_gaussians(
        s["means"], s["quats"], s["scales"], s["opacities"], s["viewmat"], s["K"], W, H
    )
    cols = sh_to_rgb(s["sh"][:, 0])
    ins = [x.detach().to(dtype) for x in (m2, con, cols, s["opacities"])]
    return ins, dep.detach().to(dtype), radii


def test_projection_matches_pose_project():
    s = random_scene(50, 64, 48, seed=1)
    R = torch.tensor([[0.96, -0.28, 0.0], [0.28, 0.96, 0.0], [0.0, 0.0, 1.0]])
    V = torch.eye(4)
    V[:3, :3], V[:3, 3] = R, torch.tensor([0.1, -0.2, 0.3])
    m2, _, dep, _ = project_gaussians(s["means"], s["quats"], s["scales"], s["opacities"], V, s["K"], 64, 48)
    pose = Pose(R.double().numpy(), np.array([0.1, -0.2, 0.3]))
    uv, z = pose.project(s["K"].double().numpy(), s["means"].double().numpy())
    np.testing.assert_allclose(m2.numpy(), uv, atol=1e-3)
    np.testing.assert_allclose(dep.numpy(), z, atol=1e-5)


def test_projection_covariance_is_ewa():
    """2D covariance = J Sigma J^T + 0.3 I with J the Jacobian of the pinhole projection at the mean."""
    s = random_scene(20, 64, 48, seed=2)
    means = s["means"].double()
    K = s["K"].double()
    m2, con, _, _ = project_gaussians(
        means,
        s["quats"].double(),
        s["scales"].double(),
        s["opacities"].double(),
        s["viewmat"].double(),
        K,
        64,
        48,
    )
    from services.splat.projection import covariances

    cov3 = covariances(s["quats"].double(), s["scales"].double())
    for i in range(len(means)):
        J = torch.autograd.functional.jacobian(lambda X: (K @ X)[:2] / X[2], means[i])
        expected = J @ cov3[i] @ J.T + 0.3 * torch.eye(2, dtype=torch.float64)
        a, b, c = con[i]
        got = torch.linalg.inv(torch.stack([torch.stack([a, b]), torch.stack([b, c])]))
        torch.testing.assert_close(got, expected, rtol=1e-6, atol=1e-9)


def test_reference_gradcheck():
    """The oracle's gradients are right (finite differences, float64)."""
    ins, dep, radii = _projected(n=20, W=16, H=12, seed=3)
    ins = [x.requires_grad_() for x in ins]

    def f(m2, con, col, op):
        c, a = rasterize_reference(
            m2, con, col, op, dep, radii, 16, 12, torch.tensor([0.2, 0.1, 0.3]).double()
        )
        return c, a

    assert float(f(*ins)[1].detach().mean()) > 0.2
    assert torch.autograd.gradcheck(f, ins, eps=1e-6, atol=1e-5, fast_mode=True)


@pytest.mark.parametrize("W,H,seed", [(64, 48, 0), (61, 45, 1)])
def test_cpu_matches_reference_2d(W, H, seed):
    ins, dep, radii = _projected(n=200, W=W, H=H, seed=seed)
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    g = torch.Generator().manual_seed(seed)
    wc, wa = (
        torch.randn(H, W, 3, generator=g, dtype=torch.float64),
        torch.randn(H, W, 1, generator=g).double(),
    )
    out = {}
    for name, fn, dt in (("ref", rasterize_reference, torch.float64), ("cpu", rasterize_cpu, torch.float32)):
        x = [t.detach().to(dt).clone().requires_grad_() for t in ins]
        c, a = fn(*x, dep.to(dt), radii, W, H, bg.to(dt))
        ((c.double() * wc).sum() + (a.double() * wa).sum()).backward()
        out[name] = (c.detach(), a.detach(), [t.grad for t in x])
    (cr, ar, gr), (cc, ac, gc) = out["ref"], out["cpu"]
    assert cc.shape == (H, W, 3) and ac.shape == (H, W, 1)
    assert 0.3 < float(ar.mean()) < 1.0  # a scene with overlaps, not an empty image
    torch.testing.assert_close(cc.double(), cr, atol=2e-5, rtol=0)
    torch.testing.assert_close(ac.double(), ar, atol=2e-5, rtol=0)
    for name, a, b in zip(("means2d", "conics", "colors", "opacities"), gc, gr, strict=True):
        assert _close(a, b), name


@pytest.mark.parametrize("mode", ["RGB", "RGB+ED"])
def test_cpu_matches_reference_through_projection(mode):
    """Gradients of every 3D parameter (means, quaternions, scales, opacities, SH of degree 3) agree."""
    W, H = 64, 48
    s = random_scene(200, W, H, seed=4, sh_degree=3)
    V = s["viewmat"].clone()
    V[:3, 3] = torch.tensor([0.05, -0.03, 0.2])
    out = {}
    for be, dt in (("reference", torch.float64), ("cpu", torch.float32)):
        p = {k: s[k].to(dt).requires_grad_() for k in PARAMS}
        c, a, info = rasterization(
            p["means"], p["quats"], p["scales"], p["opacities"], p["sh"], V.to(dt), s["K"].to(dt), W, H,
            sh_degree=3, render_mode=mode, backend=be,
        )  # fmt: skip
        info["means2d"].retain_grad()
        g = torch.Generator().manual_seed(0)
        w = torch.rand(c.shape, generator=g, dtype=torch.float64)
        ((c.double() * w).sum() + a.double().sum()).backward()
        out[be] = (c.detach().double(), {k: p[k].grad.double() for k in PARAMS}, info["means2d"].grad)
    (cr, gr, m2r), (cc, gc, m2c) = out["reference"], out["cpu"]
    torch.testing.assert_close(cc, cr, atol=5e-5 if mode == "RGB" else 2e-3, rtol=1e-5)
    for k in PARAMS:
        assert _close(gc[k], gr[k]), k
    assert _close(m2c, m2r)


def test_cpu_empty_and_background():
    W, H = 40, 30
    s = random_scene(10, W, H, seed=5)
    means = s["means"].clone()
    means[:, 2] = -means[:, 2]  # all behind the camera
    means.requires_grad_()
    bg = torch.tensor([0.3, 0.5, 0.7])
    c, a, info = rasterization(
        means, s["quats"], s["scales"], s["opacities"], s["sh"], s["viewmat"], s["K"], W, H, sh_degree=0,
        backgrounds=bg,
    )  # fmt: skip
    assert torch.allclose(c.detach(), bg.expand(H, W, 3)) and float(a.detach().abs().max()) == 0.0
    assert (info["radii"] == 0).all()
    c.sum().backward()
    assert float(means.grad.abs().max()) == 0.0


def test_render_depth_of_a_wall():
    """A wall of opaque Gaussians at z = 5: depth 5, alpha ~1, colour the wall's."""
    xs, ys = np.meshgrid(np.linspace(-4, 4, 41), np.linspace(-3, 3, 31))
    n = xs.size
    t = {
        "means": torch.tensor(np.stack([xs.ravel(), ys.ravel(), np.full(n, 5.0)], 1), dtype=torch.float32),
        "scales": torch.full((n, 3), float(np.log(0.15))),
        "quats": torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
        "opacities": torch.full((n,), 6.0),
        "sh0": ((torch.tensor([0.8, 0.4, 0.2]) - 0.5) / 0.28209479177387814).expand(n, 1, 3).clone(),
        "shN": torch.zeros(n, 0, 3),
    }
    model = splats_from_tensors(t, requires_grad=False)
    cam = Camera("PINHOLE", 48, 32, [40.0, 40.0, 24.0, 16.0])
    out = render(model, cam, Pose(np.eye(3), np.zeros(3)), backend="cpu")
    assert (
        out["color"].shape == (32, 48, 3)
        and out["depth"].shape == (32, 48)
        and out["alpha"].shape == (32, 48)
    )
    assert out["alpha"].min() > 0.99
    np.testing.assert_allclose(out["depth"], 5.0, atol=0.05)
    np.testing.assert_allclose(out["color"].mean((0, 1)), [0.8, 0.4, 0.2], atol=0.03)
    ref = render(model, cam, Pose(np.eye(3), np.zeros(3)), backend="reference")
    np.testing.assert_allclose(out["color"], ref["color"], atol=1e-4)
    # the wall 2 m nearer than the far plane and 2 m beyond the near plane: seen; outside either: gone
    for near, far, seen in ((0.01, 7.0, True), (0.01, 3.0, False), (3.0, 1e10, True), (7.0, 1e10, False)):
        out = render(model, cam, Pose(np.eye(3), np.zeros(3)), backend="cpu", near_plane=near, far_plane=far)
        assert (out["alpha"].min() > 0.99) if seen else (out["alpha"].max() == 0.0)


def test_lowered_pose_looks_at_the_same_ground_point():
    pose = look_at(np.array([0.0, -60.0, 60.0]), np.array([0.0, 0.0, 0.0]))
    assert np.allclose(pose.R[2], np.array([0, 1, -1]) / np.sqrt(2))
    assert pose.R[1] @ np.array([0, 0, 1.0]) < 0  # image y points down
    low = lowered_pose(pose, 0.5)
    assert np.allclose(low.center, [0, -60, 30])
    uv, z = low.project(np.array([[100.0, 0, 50], [0, 100, 50], [0, 0, 1]]), np.zeros((1, 3)))
    assert np.allclose(uv, [[50, 50]]) and z[0] > 0


def _wide_scene(seed: int, W: int = 64, H: int = 48) -> dict:
    """A random scene spread well beyond a camera's view (x, y up to 4x the frustum, some behind the camera,
    some near it and large), seen with an off-centre principal point."""
    s = random_scene(3000, W, H, seed=seed, sigma_px=(0.3, 12.0), depth=(-2.0, 9.0))
    s["means"][:, :2] *= 4.0
    s["K"][0, 2], s["K"][1, 2] = 0.3 * W, 0.65 * H
    return s


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_frustum_candidates_hold_every_projected_gaussian(seed):
    """The cheap cull keeps a superset of what the projection keeps (radii > 0) and drops most of the rest."""
    W, H = 64, 48
    s = _wide_scene(seed, W, H)
    args = (s["means"], s["scales"], s["opacities"], s["viewmat"], s["K"], W, H)
    ids = frustum_candidates(*args)
    _, _, _, radii = project_gaussians(
        s["means"], s["quats"], s["scales"], s["opacities"], s["viewmat"], s["K"], W, H
    )
    visible = set(torch.nonzero((radii > 0).all(-1))[:, 0].tolist())
    kept = set(ids.tolist())
    assert visible <= kept
    assert len(kept) < 0.5 * len(s["means"]) and len(visible) > 0.3 * len(kept)


@pytest.mark.parametrize("mode", ["RGB", "RGB+ED"])
def test_culling_renders_the_same_image_and_gradients(mode, monkeypatch):
    """Projecting only the frustum candidates gives the same outputs, info and gradients as projecting all."""
    import services.splat.backend as backend

    W, H = 64, 48
    s = _wide_scene(3, W, H)
    out = {}
    for cull in (True, False):
        if not cull:
            monkeypatch.setattr(
                backend, "frustum_candidates", lambda means, *a, **k: torch.arange(len(means))
            )
        p = {k: s[k].clone().requires_grad_() for k in PARAMS}
        c, a, info = rasterization(
            p["means"], p["quats"], p["scales"], p["opacities"], p["sh"], s["viewmat"], s["K"], W, H,
            sh_degree=0, render_mode=mode, backend="cpu",
        )  # fmt: skip
        info["means2d"].retain_grad()
        w = torch.rand(c.shape, generator=torch.Generator().manual_seed(0))
        ((c * w).sum() + a.sum()).backward()
        out[cull] = (c.detach(), info, {k: p[k].grad for k in PARAMS})
    (c1, i1, g1), (c0, i0, g0) = out[True], out[False]
    torch.testing.assert_close(c1, c0, atol=1e-6, rtol=1e-6)
    assert torch.equal(i1["radii"], i0["radii"])
    torch.testing.assert_close(i1["means2d"].grad, i0["means2d"].grad, atol=1e-7, rtol=1e-5)
    for k in PARAMS:
        torch.testing.assert_close(g1[k], g0[k], atol=1e-7, rtol=1e-5)


def test_bench_splat_step_runs_and_its_variants_render_alike():
    """bench/splat_step.py on a tiny scene: a row per variant and the same image from all of them."""
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).resolve().parents[1] / "bench" / "splat_step.py"
    args = ["--n", "400", "--width", "64", "--height", "48", "--steps", "1"]
    res = subprocess.run([sys.executable, str(script), *args], capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-2000:]
    for variant in ("trainer", "no cull", "conv2d SSIM", "neither"):
        assert variant in res.stdout
    diff = float(res.stdout.split("variants' images:")[1].split()[0])
    assert diff < 1e-5
