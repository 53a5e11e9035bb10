"""Torr's Geometric Robust Information Criterion (GRIC) for two-view model selection.

Convention:
    ``GRIC = sum_i min(e_i^2 / sigma^2, lambda3 * (r - d)) + lambda1 * d * n + lambda2 * k`` with
    ``lambda1 = ln r``, ``lambda2 = ln(r n)``, ``lambda3 = 2``; ``r = 4`` (two 2-D points), ``n`` = all valid
    correspondences (not only inliers), ``d`` the dimension of the model's manifold and ``k`` its number of
    parameters: E (d=3, k=5), F (d=3, k=7), H (d=2, k=8). Residuals are squared and in pixels: the Sampson
    distance through ``F = K^-T E K^-1`` for E, Torr's first-order geometric transfer error for H.
    Lower is better.
"""

from __future__ import annotations

import math

import torch
from kornia.core.check import KORNIA_CHECK, KORNIA_CHECK_SHAPE

from dfvo.geometry.two_view import homography_error_sq, sampson_sq

__all__ = ["MODEL_DIMS", "gric", "gric_essential", "gric_homography"]

MODEL_DIMS = {"E": (3, 5), "F": (3, 7), "H": (2, 8)}


def gric(residuals_sq: torch.Tensor, mask: torch.Tensor, d: int, k: int, sigma: float = 0.8,
         r: int = 4) -> torch.Tensor:
    """GRIC score of squared residuals over the valid rows.

    Convention:
        residuals_sq (B,N) in pixels^2 (non-finite: capped), mask (B,N) bool -> (B,) float64, lower is better;
        ``d``, ``k`` from :data:`MODEL_DIMS`, ``sigma`` the residual standard deviation in pixels.
    """
    KORNIA_CHECK_SHAPE(residuals_sq, ["B", "N"])
    KORNIA_CHECK(mask.shape == residuals_sq.shape, f"gric: mask {tuple(mask.shape)} must match residuals "
                                                   f"{tuple(residuals_sq.shape)}")
    KORNIA_CHECK(sigma > 0 and r > d, f"gric: need sigma > 0 and r > d; got sigma={sigma}, r={r}, d={d}")
    res = residuals_sq.to(torch.float64)
    n = mask.sum(-1).to(torch.float64)
    cap = 2.0 * (r - d)
    rho = torch.where(torch.isfinite(res), (res / sigma**2).clamp(max=cap), torch.full_like(res, cap))
    rho = torch.where(mask, rho, torch.zeros_like(rho)).sum(-1)
    lam1, lam2 = math.log(r), torch.log(r * n.clamp_min(1.0))
    return rho + lam1 * d * n + lam2 * k


def gric_essential(E: torch.Tensor, K: torch.Tensor, pts_i: torch.Tensor, pts_j: torch.Tensor, mask: torch.Tensor,
                   sigma: float = 0.8) -> torch.Tensor:
    """GRIC of essential matrices on pixel pairs, with Sampson residuals through ``F = K^-T E K^-1``.

    Convention:
        E (B,3,3) with ``x_j^T E x_i = 0`` (normalised coordinates), K (B,3,3), pts_i / pts_j (B,N,2) pixels in
        images i (previous) and j (current), mask (B,N) -> (B,) float64.
    """
    Kinv = torch.linalg.inv(K.to(torch.float64))
    F = Kinv.transpose(-1, -2) @ E.to(torch.float64) @ Kinv
    res = sampson_sq(F[:, None], pts_i.to(torch.float64), pts_j.to(torch.float64))[:, 0]
    return gric(res, mask, *MODEL_DIMS["E"], sigma=sigma)


def gric_homography(H: torch.Tensor, pts_i: torch.Tensor, pts_j: torch.Tensor, mask: torch.Tensor,
                    sigma: float = 0.8) -> torch.Tensor:
    """GRIC of homographies on pixel pairs, with Torr's geometric transfer residuals.

    Convention:
        H (B,3,3) with ``x_j ~ H x_i`` (pixels, i previous, j current), pts_i / pts_j (B,N,2), mask (B,N)
        -> (B,) float64.
    """
    res = homography_error_sq(H.to(torch.float64)[:, None], pts_i.to(torch.float64), pts_j.to(torch.float64))[:, 0]
    return gric(res, mask, *MODEL_DIMS["H"], sigma=sigma)
