"""The homography's decomposition against planes and motions built by hand."""

from __future__ import annotations

import math

import pytest
import torch

from dfvo.geometry.homography import decompose_homography

D = torch.float64
K = torch.tensor([[420.5, 0.0, 355.2], [0.0, 420.6, 250.3], [0.0, 0.0, 1.0]], dtype=D)


def rotation(axis: list[float], deg: float) -> torch.Tensor:
    a = torch.tensor(axis, dtype=D)
    a = a / a.norm()
    A = torch.tensor([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]], dtype=D)
    th = math.radians(deg)
    return torch.eye(3, dtype=D) + math.sin(th) * A + (1 - math.cos(th)) * A @ A


def plane_view(n: torch.Tensor, d: float, R: torch.Tensor, t: torch.Tensor, seed: int = 0):
    """Pixels of 100 points of the plane n^T X = d seen from camera i and from camera j (X_j = R X_i + t), and the
    pixel homography they induce (times an arbitrary factor, negative too)."""
    g = torch.Generator().manual_seed(seed)
    n = n / n.norm()
    rays = torch.cat([torch.rand(200, 2, generator=g, dtype=D) * 1.2 - 0.6, torch.ones(200, 1, dtype=D)], 1)
    rays = rays[rays @ n > 0.05][:100]  # the rays that meet the plane in front of the camera
    X = rays * (d / (rays @ n))[:, None]
    Xj = X @ R.T + t
    assert (X[:, 2] > 0).all() and (Xj[:, 2] > 0).all()
    pix = lambda P: (P @ K.T)[:, :2] / (P @ K.T)[:, 2:]  # noqa: E731
    H = -3.7 * K @ (R + torch.outer(t, n) / d) @ torch.linalg.inv(K)
    return pix(X)[None], pix(Xj)[None], H[None]


@pytest.mark.parametrize("case", ["desk below", "wall ahead, sideways", "tilted, turning"])
def test_one_decomposition_is_the_true_motion_and_two_put_the_plane_in_front(case: str) -> None:
    """Exact plane and motion (a hand-held camera's: a few cm, a few degrees): one of the four decompositions is the
    true (R, t / d, n) to 1e-9 and puts every point in front of camera i, its negation none; of the other pair at
    most one puts them all in front (the ambiguity a prior must resolve)."""
    n, d, R, t = {
        "desk below": (torch.tensor([0.0, 1.0, 0.3], dtype=D), 0.6, rotation([1, 0, 0], 3.0),
                       torch.tensor([0.02, 0.0, 0.05], dtype=D)),
        "wall ahead, sideways": (torch.tensor([0.1, 0.0, 1.0], dtype=D), 1.5, rotation([0, 1, 0], -4.0),
                                 torch.tensor([0.08, 0.01, 0.0], dtype=D)),
        "tilted, turning": (torch.tensor([0.3, 0.5, 1.0], dtype=D), 1.0, rotation([1, 2, 0.5], 7.0),
                            torch.tensor([-0.03, 0.04, 0.06], dtype=D)),
    }[case]
    pi, pj, H = plane_view(n, d, R, t)
    out = decompose_homography(H, K[None], pi, pj, torch.ones(1, 100, dtype=torch.bool))
    n_true = n / n.norm()
    err = [float((out.R[0, m] - R).abs().max() + (out.t_over_d[0, m] - t / d).abs().max()
                 + (out.n[0, m] - n_true).abs().max()) for m in range(4)]
    assert min(err) < 1e-9, err
    true = err.index(min(err))
    assert float(out.in_front[0, true]) == 1.0 and float(out.in_front[0, true ^ 1]) == 0.0  # it and its negation
    assert 1 <= int((out.in_front[0] == 1.0).sum()) <= 2  # the other pair: at most one of them, both signs split
    for m in range(4):
        assert torch.allclose(out.R[0, m] @ out.R[0, m].T, torch.eye(3, dtype=D), atol=1e-9)
        assert float(torch.linalg.det(out.R[0, m])) == pytest.approx(1.0, abs=1e-9)


def test_pure_rotation_has_no_translation() -> None:
    """A camera that only rotates: H = K R K^-1, every decomposition has R and t / d = 0."""
    R = rotation([0.2, 1, 0.1], 5.0)
    pi, pj, H = plane_view(torch.tensor([0.0, 0.0, 1.0], dtype=D), 2.0, R, torch.zeros(3, dtype=D))
    out = decompose_homography(H, K[None], pi, pj, torch.ones(1, 100, dtype=torch.bool))
    assert (out.R[0] - R).abs().max() < 1e-6
    assert out.t_over_d[0].norm(dim=-1).max() < 1e-6


def test_a_degenerate_homography_beside_a_plane_s_has_no_decomposition_and_does_not_stop_the_batch() -> None:
    """A batch of three pairs: a plane's exact homography, the rank-1 matrix a RANSAC fit to collinear points
    returned on a hand-held world (its normalisation by the middle singular value overflowed and eigh raised), and a
    non-finite one. The plane's pair decomposes as alone; the other two put nothing in front (no decomposition)."""
    R, t = rotation([1, 2, 0.5], 7.0), torch.tensor([-0.03, 0.04, 0.06], dtype=D)
    pi, pj, H = plane_view(torch.tensor([0.3, 0.5, 1.0], dtype=D), 1.0, R, t)
    rank1 = torch.zeros(1, 3, 3, dtype=D)
    rank1[0, 1, 0], rank1[0, 1, 2] = 1.0202, -230.5693
    nan = torch.full((1, 3, 3), float("nan"), dtype=D)
    mask = torch.ones(3, 100, dtype=torch.bool)
    out = decompose_homography(torch.cat([H, rank1, nan]), K[None].expand(3, 3, 3), pi.expand(3, -1, -1),
                               pj.expand(3, -1, -1), mask)
    alone = decompose_homography(H, K[None], pi, pj, mask[:1])
    assert torch.equal(out.in_front[0], alone.in_front[0]) and torch.allclose(out.R[0], alone.R[0], atol=1e-12)
    assert float(out.in_front[1:].abs().max()) == 0.0
    assert bool(torch.isfinite(out.R[1:]).all()) and bool(torch.isfinite(out.t_over_d[1:]).all())
