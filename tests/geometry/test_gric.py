"""GRIC: the formula by hand, Sampson residuals in pixels, and model selection on degenerate scenes."""

import math

import pytest
import torch

from dfvo.geometry.camera import project_points, transform_points
from dfvo.geometry.gric import gric, gric_essential, gric_homography
from dfvo.geometry.se3 import pose_from_axis_angle
from dfvo.geometry.two_view import find_essential_ransac, find_homography_ransac, sampson_sq
from dfvo.tracking.model_selection import prefer_pnp_flow, prefer_pnp_gric

torch.set_num_threads(1)
K = torch.tensor([[[700.0, 0.0, 320.0], [0.0, 700.0, 96.0], [0.0, 0.0, 1.0]]], dtype=torch.float64)


def test_gric_formula_by_hand():
    res = torch.tensor([[0.0, 0.64, 6.4, 100.0, 5.0]], dtype=torch.float64)
    mask = torch.tensor([[True, True, True, True, False]])
    n, sigma2 = 4, 0.64
    # E: d=3, k=5 -> cap lambda3 (r - d) = 2
    rho_e = 0 + 1 + 2 + 2
    want_e = rho_e + math.log(4) * 3 * n + math.log(4 * n) * 5
    assert gric(res, mask, 3, 5) == pytest.approx(want_e)
    # H: d=2, k=8 -> cap 4
    rho_h = 0 + 0.64 / sigma2 + 4 + 4
    want_h = rho_h + math.log(4) * 2 * n + math.log(4 * n) * 8
    assert gric(res, mask, 2, 8) == pytest.approx(want_h)


def test_sampson_in_pixels_matches_opencv():
    cv2 = pytest.importorskip("cv2")
    g = torch.Generator().manual_seed(0)
    F = torch.randn(1, 1, 3, 3, generator=g, dtype=torch.float64)
    a = torch.rand(1, 20, 2, generator=g, dtype=torch.float64) * 600
    b = torch.rand(1, 20, 2, generator=g, dtype=torch.float64) * 600
    ours = sampson_sq(F, a, b)[0, 0]
    for k in range(20):
        ref = cv2.sampsonDistance(torch.cat([a[0, k], torch.ones(1, dtype=torch.float64)]).numpy()[:, None],
                                  torch.cat([b[0, k], torch.ones(1, dtype=torch.float64)]).numpy()[:, None],
                                  F[0, 0].numpy())
        assert float(ours[k]) == pytest.approx(ref, rel=1e-9)


def scene(kind: str, N: int = 600):
    g = torch.Generator().manual_seed(1)
    z = torch.full((1, N), 15.0, dtype=torch.float64) if kind == "planar" else \
        torch.rand(1, N, generator=g, dtype=torch.float64) * 40 + 5
    X = torch.stack([(torch.rand(1, N, generator=g, dtype=torch.float64) - 0.5) * 0.8 * z,
                     (torch.rand(1, N, generator=g, dtype=torch.float64) - 0.5) * 0.25 * z, z], -1)
    t = torch.zeros(1, 3, dtype=torch.float64) if kind == "rotation" else torch.tensor([[0.05, 0.0, -1.0]]).double()
    T = pose_from_axis_angle(torch.tensor([[0.0, 0.03, 0.01]], dtype=torch.float64), t)
    pi, _ = project_points(X, K)
    pj, _ = project_points(transform_points(T, X), K)
    noise = 0.2 * torch.randn(pj.shape, generator=g, dtype=torch.float64)
    return pi, pj + noise


@pytest.mark.parametrize("kind,pnp", [("general", False), ("rotation", True), ("planar", True)])
def test_gric_chooses_pnp_on_degenerate_scenes(kind, pnp):
    pi, pj = scene(kind)
    mask = torch.ones(pi.shape[:2], dtype=torch.bool)
    gens = [torch.Generator().manual_seed(0)]
    E = find_essential_ransac(pi, pj, mask, K, threshold_px=0.5, generators=gens).model
    H = find_homography_ransac(pi, pj, mask, threshold_px=1.0, generators=gens).model
    g_e, g_h = gric_essential(E, K, pi, pj, mask), gric_homography(H, pi, pj, mask)
    assert bool(prefer_pnp_gric(g_e, g_h)[0]) is pnp, (float(g_e), float(g_h))


def test_flow_magnitude_selection():
    pi = torch.zeros(2, 5, 2)
    pj = pi.clone()
    pj[1] += 10.0
    mask = torch.ones(2, 5, dtype=torch.bool)
    assert prefer_pnp_flow(pi, pj, mask, 5.0).tolist() == [True, False]
