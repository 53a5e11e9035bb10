"""Motion and plane from a plane-induced homography: the analytic decomposition (Ma, Soatto, Košecká & Sastry, *An
Invitation to 3-D Vision*, 2004, sec. 5.3.3), batched in float64.

A plane ``n^T X_i = d`` (``X_i`` in camera i, ``n`` its unit normal, ``d > 0`` the camera's distance to it) seen by two
cameras related by ``T_cur_prev = [R | t]`` (``X_j = R X_i + t``) induces the calibrated homography
``H_c = K^-1 H K = lambda (R + t n^T / d)`` on normalised coordinates. Normalised by its middle singular value and
signed so that ``x_j^T H_c x_i > 0`` on the correspondences (both depths positive), it has four decompositions
``(R, t / d, n)``: two pairs of opposite signs. The positive-depth condition ``n^T x_i > 0`` on the plane's points
(``X_i = z x_i`` with ``z > 0`` and ``n^T X_i = d > 0``) leaves two, which a third view or a prior must tell apart
(:func:`decompose_homography` returns all four with the fraction of points each puts in front).

Convention:
    H (B,3,3) pixel homography ``x_j ~ H x_i`` (i previous, j current); K (B,3,3); pts_i, pts_j (B,N,2) pixels;
    mask (B,N) bool. Candidates: R (B,4,3,3), t_over_d (B,4,3), n (B,4,3) unit normals in camera i, in_front (B,4)
    the fraction of valid rows with ``n^T x_i > 0``. A pure rotation (the singular values all 1) gives ``t / d = 0``
    and an undefined normal. A homography that is not finite or not of full rank (a RANSAC fit to collinear points)
    has no decomposition: its ``in_front`` is 0 for all four.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from kornia.core.check import KORNIA_CHECK, KORNIA_CHECK_SHAPE

from dfvo.geometry.two_view import normalise_points

__all__ = ["HomographyDecomposition", "decompose_homography"]

_MIN_SINGULAR_RATIO = 1e-9  # smallest / largest singular value below which a homography counts as degenerate


@dataclass
class HomographyDecomposition:
    """The four decompositions of each pair's homography (see the module docstring for the shapes)."""

    R: torch.Tensor
    t_over_d: torch.Tensor
    n: torch.Tensor
    in_front: torch.Tensor


def _columns(*vectors: torch.Tensor) -> torch.Tensor:
    return torch.stack(vectors, -1)


def decompose_homography(H: torch.Tensor, K: torch.Tensor, pts_i: torch.Tensor, pts_j: torch.Tensor,
                         mask: torch.Tensor) -> HomographyDecomposition:
    """The four ``(R, t / d, n)`` of each pixel homography ``H`` (module docstring), with the fraction of the valid
    correspondences each puts in front of camera i; the correspondences also fix the homography's sign."""
    KORNIA_CHECK_SHAPE(H, ["B", "3", "3"])
    KORNIA_CHECK_SHAPE(pts_i, ["B", "N", "2"])
    KORNIA_CHECK(pts_j.shape == pts_i.shape and mask.shape == pts_i.shape[:2],
                 f"decompose_homography: pts_j {tuple(pts_j.shape)} and mask {tuple(mask.shape)} must match pts_i "
                 f"{tuple(pts_i.shape)}")
    Kd = K.to(torch.float64)
    eye = torch.eye(3, dtype=torch.float64, device=H.device).expand_as(Kd)
    H64 = H.to(torch.float64)
    finite = torch.isfinite(H64).all(-1).all(-1)
    Hc = torch.linalg.solve(Kd, torch.where(finite[:, None, None], H64, eye)) @ Kd
    sv = torch.linalg.svdvals(Hc)
    # a plane seen from two cameras induces a full-rank homography; a RANSAC fit to collinear points may be rank 1-2
    # (its normalisation would overflow): no decomposition for those pairs (in_front 0, the identity in its place)
    usable = finite & (sv[:, 2] > _MIN_SINGULAR_RATIO * sv[:, 0])
    Hc = torch.where(usable[:, None, None], Hc / sv[:, 1, None, None].clamp_min(1e-300), eye)
    xi, xj = (torch.nn.functional.pad(normalise_points(p.to(torch.float64), Kd), (0, 1), value=1.0)
              for p in (pts_i, pts_j))
    agreement = torch.where(mask, torch.einsum("bnr,brc,bnc->bn", xj, Hc, xi), torch.zeros_like(xi[..., 0]))
    Hc = Hc * torch.where(agreement.sum(-1) < 0, -1.0, 1.0)[:, None, None]
    evals, V = torch.linalg.eigh(Hc.transpose(-1, -2) @ Hc)  # ascending: sigma3^2 <= 1 <= sigma1^2
    V = V * torch.where(torch.linalg.det(V) < 0, -1.0, 1.0)[:, None, None]
    s3, s1 = evals[:, 0].clamp(max=1.0), evals[:, 2].clamp(min=1.0)
    v1, v2, v3 = V[..., 2], V[..., 1], V[..., 0]
    a, b = (1.0 - s3).clamp_min(0).sqrt()[:, None], (s1 - 1.0).clamp_min(0).sqrt()[:, None]
    c = (s1 - s3).clamp_min(1e-300).sqrt()[:, None]
    Rs, ts, ns = [], [], []
    for u in ((a * v1 + b * v3) / c, (a * v1 - b * v3) / c):
        Hv2, Hu = (Hc @ v2[..., None])[..., 0], (Hc @ u[..., None])[..., 0]
        U = _columns(v2, u, torch.linalg.cross(v2, u, dim=-1))
        W = _columns(Hv2, Hu, torch.linalg.cross(Hv2, Hu, dim=-1))
        R = W @ U.transpose(-1, -2)
        n = torch.linalg.cross(v2, u, dim=-1)
        t = ((Hc - R) @ n[..., None])[..., 0]
        Rs += [R, R]
        ts += [t, -t]
        ns += [n, -n]
    R, t, n = torch.stack(Rs, 1), torch.stack(ts, 1), torch.stack(ns, 1)
    front = (torch.einsum("bmc,bnc->bmn", n, xi) > 0) & mask[:, None]
    in_front = front.sum(-1).to(torch.float64) / mask.sum(-1, keepdim=True).clamp_min(1).to(torch.float64)
    in_front = torch.where(usable[:, None], in_front, torch.zeros_like(in_front))
    return HomographyDecomposition(R, t, n, in_front)
