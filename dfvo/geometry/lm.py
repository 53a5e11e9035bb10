"""Levenberg-Marquardt refinement of camera poses on SE(3) from 3-D/2-D correspondences.

Convention:
    ``points_3d`` (B,N,3) are in frame i (previous), ``pixels`` (B,N,2) in image j (current), ``K`` (B,3,3)
    the intrinsics of image j and ``T_cur_prev`` (B,4,4) maps frame-i points into camera j. The pose is
    perturbed on the left, ``T <- Exp(delta) T`` with ``delta = (rho, phi)`` (translation first), retracted as
    ``R <- exp(phi) R, t <- exp(phi) t + rho`` which has the same first-order model
    ``X_c <- X_c + rho + phi x X_c``. All arithmetic is float64 internally.
"""

from __future__ import annotations

import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix


def reprojection_residuals(T: torch.Tensor, points_3d: torch.Tensor, pixels: torch.Tensor, K: torch.Tensor,
                           eps: float = 1e-9) -> tuple[torch.Tensor, torch.Tensor]:
    """Residuals ``project(K, T X) - pixel``.

    Args:
        T: (B,4,4) ``T_cur_prev``.
        points_3d: (B,N,3) points in frame i.
        pixels: (B,N,2) observed pixels in image j.
        K: (B,3,3) intrinsics of image j.

    Returns:
        residuals (B,N,2) in pixels, and (B,N,3) points in camera j. Points with depth <= eps get a huge residual.

    Convention:
        ``project(K, X) = K[:2, :2] [x / z, y / z] + K[:2, 2]`` (skew included); see the module docstring.
    """
    Xc = points_3d @ T[:, :3, :3].transpose(1, 2) + T[:, None, :3, 3]
    z = Xc[..., 2:3]
    safe_z = torch.where(z > eps, z, torch.ones_like(z))
    xy = Xc[..., :2] / safe_z
    uv = xy @ K[:, :2, :2].transpose(1, 2) + K[:, None, :2, 2]
    res = torch.where(z > eps, uv - pixels, torch.full_like(uv, 1e6))
    return res, Xc


def refine_pose_lm(points_3d: torch.Tensor, pixels: torch.Tensor, weights: torch.Tensor, K: torch.Tensor,
                   T_init: torch.Tensor, iterations: int = 20, lambda_init: float = 1e-3,
                   tol: float = 1e-12) -> tuple[torch.Tensor, torch.Tensor]:
    """Minimise ``sum_n w_n ||project(K, T X_n) - x_n||^2`` over ``T`` in SE(3) with Levenberg-Marquardt.

    Args:
        points_3d: (B,N,3) points in frame i.
        pixels: (B,N,2) pixels in image j.
        weights: (B,N) non-negative weights (a bool mask works: 0/1).
        K: (B,3,3) intrinsics of image j.
        T_init: (B,4,4) initial ``T_cur_prev``.
        iterations: maximum LM iterations (each batch element stops improving on its own).
        lambda_init: initial damping (relative to the diagonal of the normal matrix).
        tol: relative cost decrease below which an element counts as converged (an element also stops once
            its damping has grown past 1e4, i.e. after repeated rejected steps at a minimum).

    Returns:
        T: (B,4,4) refined ``T_cur_prev`` (dtype of ``T_init``), and the final weighted cost (B,) in pixels^2.

    Convention:
        Left perturbation ``T <- Exp(delta) T`` (see the module docstring); float64 internally.
    """
    out_dtype = T_init.dtype
    X = points_3d.to(torch.float64)
    x = pixels.to(torch.float64)
    w = weights.to(torch.float64)
    Kd = K.to(torch.float64)
    T = T_init.to(torch.float64).clone()
    B = X.shape[0]
    lam = torch.full((B,), lambda_init, dtype=torch.float64, device=X.device)
    eye6 = torch.eye(6, dtype=torch.float64, device=X.device)

    def cost_of(T_: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        r, Xc = reprojection_residuals(T_, X, x, Kd)
        return (w * (r * r).sum(-1)).sum(-1), r, Xc

    cost, r, Xc = cost_of(T)
    active = torch.ones(B, dtype=torch.bool, device=X.device)
    for _ in range(iterations):
        # Jacobian of the normalised projection (a, b) = (x/z, y/z) w.r.t. (rho, phi), then through K's 2x2 block
        iz = 1.0 / Xc[..., 2].clamp_min(1e-9)
        a, b = Xc[..., 0] * iz, Xc[..., 1] * iz
        zero = torch.zeros_like(a)
        Ja = torch.stack([iz, zero, -a * iz, -a * b, 1.0 + a * a, -b], -1)
        Jb = torch.stack([zero, iz, -b * iz, -(1.0 + b * b), a * b, a], -1)
        J = torch.stack([Kd[:, None, 0, 0, None] * Ja + Kd[:, None, 0, 1, None] * Jb,
                         Kd[:, None, 1, 1, None] * Jb], -2).reshape(B, -1, 6)  # (B,2N,6)
        wJ = J * w.repeat_interleave(2, dim=1).unsqueeze(-1)
        H = wJ.transpose(1, 2) @ J
        g = (wJ * r.reshape(B, -1, 1)).sum(1)
        diag = torch.diagonal(H, dim1=-2, dim2=-1).clamp_min(1e-12)
        A = H + lam[:, None, None] * torch.diag_embed(diag) + 1e-12 * eye6
        delta = -torch.linalg.solve(A, g.unsqueeze(-1)).squeeze(-1)
        delta = torch.nan_to_num(delta) * active[:, None]
        dR = axis_angle_to_rotation_matrix(delta[:, 3:])
        T_new = T.clone()
        T_new[:, :3, :3] = dR @ T[:, :3, :3]
        T_new[:, :3, 3] = (dR @ T[:, :3, 3:4]).squeeze(-1) + delta[:, :3]
        new_cost, new_r, new_Xc = cost_of(T_new)
        better = (new_cost < cost) & active & torch.isfinite(new_cost)
        rel = (cost - new_cost) / cost.clamp_min(1e-300)
        T = torch.where(better[:, None, None], T_new, T)
        r = torch.where(better[:, None, None], new_r, r)
        Xc = torch.where(better[:, None, None], new_Xc, Xc)
        lam = torch.where(better, lam * 0.1, lam * 10.0).clamp(1e-12, 1e12)
        active = active & ~(better & (rel < tol)) & (lam < 1e4) & (cost > 0)
        cost = torch.where(better, new_cost, cost)
        if not bool(active.any()):
            break
    return T.to(out_dtype), cost.to(out_dtype)
