"""gsplat (CUDA) backend against the plain-PyTorch reference; skipped without a CUDA device and gsplat."""

import pytest
import torch

from services.splat.backend import gsplat_available, rasterization, resolve_backend
from services.splat.synthetic import random_scene

pytestmark = pytest.mark.skipif(
    not (torch.cuda.is_available() and gsplat_available()), reason="needs a CUDA device and gsplat"
)
PARAMS = ("means", "quats", "scales", "opacities", "sh")


def test_auto_picks_cuda():
    assert resolve_backend("auto") == "cuda"


@pytest.mark.parametrize("mode", ["RGB", "RGB+ED"])
def test_gsplat_matches_reference(mode):
    W, H = 64, 48
    s = random_scene(200, W, H, seed=4, sh_degree=3)
    s["opacities"] = s["opacities"].clamp_max(0.9)  # away from the alpha clamp
    out = {}
    for be in ("reference", "cuda"):
        p = {k: s[k].clone().requires_grad_() for k in PARAMS}
        c, a, info = rasterization(
            p["means"], p["quats"], p["scales"], p["opacities"], p["sh"], s["viewmat"], s["K"], W, H,
            sh_degree=3, render_mode=mode, backend=be,
        )  # fmt: skip
        g = torch.Generator().manual_seed(0)
        w = torch.rand(c.shape, generator=g).to(c.device)
        ((c * w).sum() + a.sum()).backward()
        out[be] = (c.detach().cpu(), a.detach().cpu(), {k: p[k].grad.cpu() for k in PARAMS})
    (cr, ar, gr), (cc, ac, gc) = out["reference"], out["cuda"]
    # gsplat bounds Gaussians a little differently (tile-level culling, radii), so compare loosely
    assert float((cc[..., :3] - cr[..., :3]).abs().mean()) < 2e-3
    assert float((ac - ar).abs().mean()) < 2e-3
    for k in PARAMS:
        num = float((gc[k] - gr[k]).norm())
        assert num <= 0.05 * float(gr[k].norm()) + 1e-6, k


def test_trainer_on_cuda(tmp_path):
    from services.splat.train import SceneData, Trainer
    from tests.test_splat_train import _gt_model, _tiny_conf, _views

    model, pts, cols = _gt_model()
    data = SceneData.from_views(_views(model), pts, cols * 0.8, test_every=0)
    tr = Trainer(_tiny_conf(steps=30), data, tmp_path, backend="cuda")
    tr.train(progress=False)
    assert tr.history[-1]["loss"] < tr.history[0]["loss"]
