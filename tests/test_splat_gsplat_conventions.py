"""The CPU backend's conventions against gsplat's own plain-PyTorch implementation (gsplat.cuda._torch_impl).

The CUDA backend hands our Gaussians, viewmats and K to `gsplat.rasterization` as they are; these tests
check, on the CPU, that gsplat reads them as our projection and spherical harmonics do: quaternion order
(w, x, y, z), scales not log, viewmat cam_from_world, K in the COLMAP pixel convention, the Jacobian's
clamp, the 2D low-pass filter, the conic layout, the bounding radii and the SH basis. gsplat's
pure-PyTorch reference needs no GPU (the wheel is pure Python; its CUDA kernels build on first use only).
"""

import pytest
import torch

from services.splat.projection import EPS2D, FAR, NEAR, covariances, project_gaussians, quat_to_rotmat
from services.splat.sh import spherical_harmonics
from services.splat.synthetic import random_scene

gs = pytest.importorskip("gsplat.cuda._torch_impl", reason="needs the gsplat package (pip install gsplat)")


def _camera_off_axis(K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """A rotated, translated camera with an off-centre principal point (so no convention hides)."""
    ang = torch.tensor([0.2, -0.3, 0.1])
    R = quat_to_rotmat(torch.cat([torch.tensor([1.0]), 0.5 * ang])[None])[0]
    V = torch.eye(4)
    V[:3, :3] = R
    V[:3, 3] = torch.tensor([0.3, -0.2, 0.5])
    K = K.clone()
    K[0, 2] += 5.5
    K[1, 2] -= 3.25
    K[1, 1] *= 1.1
    return V, K


def _scene(n: int = 400, W: int = 96, H: int = 72) -> dict:
    s = random_scene(n, W, H, seed=7, sigma_px=(0.3, 6.0), depth=(1.5, 9.0), sh_degree=3)
    V, K = _camera_off_axis(s["K"])
    # the scene in front of the identity camera, moved so that the new camera sees it the same way
    Vinv = torch.linalg.inv(V)
    s["means"] = s["means"] @ Vinv[:3, :3].T + Vinv[:3, 3]
    s["viewmat"], s["K"], s["W"], s["H"] = V, K, W, H
    return s


def _gsplat_projection(s: dict):
    covars, _ = gs._quat_scale_to_covar_preci(s["quats"], s["scales"], True, False, triu=False)
    radii, means2d, depths, conics, _ = gs._fully_fused_projection(
        s["means"], covars, s["viewmat"][None], s["K"][None], s["W"], s["H"],
        eps2d=EPS2D, near_plane=NEAR, far_plane=FAR,
    )  # fmt: skip
    return covars, radii[0], means2d[0], depths[0], conics[0]


def test_covariances_match_gsplat():
    s = _scene()
    covars, *_ = _gsplat_projection(s)
    torch.testing.assert_close(covariances(s["quats"], s["scales"]), covars, rtol=1e-5, atol=1e-9)


def test_projection_matches_gsplat():
    s = _scene()
    _, radii_g, means2d_g, depths_g, conics_g = _gsplat_projection(s)
    means2d, conics, depths, radii = project_gaussians(
        s["means"], s["quats"], s["scales"], s["opacities"], s["viewmat"], s["K"], s["W"], s["H"]
    )
    torch.testing.assert_close(depths, depths_g, rtol=1e-6, atol=1e-6)
    ours = (radii > 0).all(-1)
    theirs = (radii_g > 0).all(-1)
    assert int(ours.sum()) > 300 and int((~theirs).sum()) > 5  # some in view, some culled
    torch.testing.assert_close(means2d[ours], means2d_g[ours], rtol=1e-5, atol=1e-3)
    torch.testing.assert_close(conics[ours], conics_g[ours], rtol=1e-4, atol=1e-6)
    # gsplat's CUDA kernel bounds a Gaussian at min(3.33, sqrt(2 ln(opacity * 255))) standard deviations
    # (where its alpha falls below 1/255), its PyTorch reference at 3.33: ours is the kernel's bound, so
    # it never exceeds the reference's and keeps no Gaussian the reference culls
    assert not (ours & ~theirs).any()
    assert (radii[ours] <= radii_g[ours]).all()
    a, b, c = conics_g.unbind(-1)
    var = torch.stack([c, a], -1) / (a * c - b * b)[:, None]  # the 2D covariance's diagonal (x, y)
    sigmas = torch.sqrt((2.0 * torch.log(s["opacities"] * 255.0)).clamp_min(0)).clamp_max(3.33)
    kernel = torch.ceil(sigmas[:, None] * var.sqrt())
    assert ((radii[ours] - kernel[ours]).abs() <= 1).all()  # a ceil may round the other way


def test_spherical_harmonics_match_gsplat():
    g = torch.Generator().manual_seed(3)
    dirs = torch.randn(500, 3, generator=g) * torch.tensor([1.0, 2.0, 0.5])
    coeffs = torch.randn(500, 16, 3, generator=g)
    for degree in range(4):
        torch.testing.assert_close(
            spherical_harmonics(degree, dirs, coeffs),
            gs._spherical_harmonics(degree, dirs, coeffs),
            rtol=1e-5, atol=1e-5,
        )  # fmt: skip
