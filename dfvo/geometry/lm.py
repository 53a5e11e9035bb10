"""Levenberg-Marquardt: one batched core (:func:`levenberg_marquardt`) and the refinement of camera poses on SE(3)
from 3-D/2-D correspondences (:func:`refine_pose_lm`; the essential-matrix refinement of
:mod:`dfvo.geometry.essential_refine` runs on the same core).

The core solves ``(H + lambda diag(H)) delta = -g`` for every problem of the batch, keeps a step only where it lowers
that problem's cost (then ``lambda /= 10``, else ``lambda *= 10``), and stops a problem when a kept step lowers its
cost by at most ``tol`` relatively, when its damping passes ``max_lambda`` (repeated rejected steps at a minimum), or
when its cost is 0. The callers pass today's limits: PnP ``max_lambda`` 1e4 with a diagonal floor and ridge of 1e-12,
the essential matrix 1e6 with 1e-300 (it works in normalised coordinates, whose costs are ~1e-6 of pixel ones).

Convention (SE(3) refinement):
    ``points_3d`` (B,N,3) are in frame i (previous), ``pixels`` (B,N,2) in image j (current), ``K`` (B,3,3)
    the intrinsics of image j and ``T_cur_prev`` (B,4,4) maps frame-i points into camera j. The pose is
    perturbed on the left, ``T <- Exp(delta) T`` with ``delta = (rho, phi)`` (translation first), retracted as
    ``R <- exp(phi) R, t <- exp(phi) t + rho`` which has the same first-order model
    ``X_c <- X_c + rho + phi x X_c``. All arithmetic is float64 internally.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix

__all__ = ["levenberg_marquardt", "reprojection_residuals", "refine_pose_lm"]

Tensors = tuple[torch.Tensor, ...]


def _select(mask: torch.Tensor, new: Tensors, old: Tensors) -> Tensors:
    """Per problem (dim 0): ``new`` where ``mask`` (B,), else ``old``."""
    return tuple(torch.where(mask.view(-1, *([1] * (n.dim() - 1))), n, o) for n, o in zip(new, old, strict=True))


def levenberg_marquardt(state: Tensors, evaluate: Callable[[Tensors], tuple[torch.Tensor, Tensors]],
                        linearise: Callable[[Tensors, Tensors], tuple[torch.Tensor, torch.Tensor, Tensors]],
                        retract: Callable[[Tensors, torch.Tensor, Tensors], Tensors], active: torch.Tensor, *,
                        iterations: int, lambda_init: float, tol: float, max_lambda: float, diagonal_floor: float,
                        ridge: float) -> tuple[Tensors, torch.Tensor]:
    """Batched Levenberg-Marquardt over B independent problems of D parameters (float64).

    Args:
        state: the parameters, tensors with the problems along dim 0 (e.g. ``(T,)`` (B,4,4) or ``(R, t)``).
        evaluate: ``state -> (cost (B,), aux)``; ``aux`` (tensors, problems along dim 0) is what ``linearise`` needs
            besides the state (e.g. the residuals), so they are computed once per accepted step.
        linearise: ``(state, aux) -> (H (B,D,D), g (B,D), frame)``: the Gauss-Newton matrix and the gradient
            ``J^T W r`` at the state, and what the step is expressed in (e.g. a tangent basis; may be empty). It runs
            only when some problem moved and is kept per problem until that problem moves again.
        retract: ``(state, delta (B,D), frame) -> state``: the state moved by ``delta``.
        active: (B,) bool, the problems to solve (the others are returned as given).
        iterations: maximum steps. lambda_init: initial damping, relative to the diagonal of ``H``.
        tol: a kept step that lowers the cost by at most ``tol * cost`` ends the problem (converged).
        max_lambda: a problem stops once its damping has grown past this (repeated rejected steps).
        diagonal_floor: the damping is ``lambda * max(diag(H), diagonal_floor)``; ridge: ``ridge * I`` is added.

    Returns:
        the final state and cost (B,).
    """
    cost, aux = evaluate(state)
    B, dev = cost.shape[0], cost.device
    lam = torch.full((B,), lambda_init, dtype=torch.float64, device=dev)
    moved = torch.ones_like(active)
    H = g = None
    frame: Tensors = ()
    eye = None
    for _ in range(iterations):
        if not bool(active.any()):
            break
        if bool(moved.any()):  # the normal equations change only where the last step was taken
            H_new, g_new, frame_new = linearise(state, aux)
            if H is None:
                H, g, frame = H_new, g_new, frame_new
                eye = torch.eye(H.shape[-1], dtype=H.dtype, device=dev)
            else:
                H, g = torch.where(moved[:, None, None], H_new, H), torch.where(moved[:, None], g_new, g)
                frame = _select(moved, frame_new, frame)
        damping = lam[:, None] * torch.diagonal(H, dim1=-2, dim2=-1).clamp_min(diagonal_floor)
        A = H + damping.diag_embed() + ridge * eye
        delta, info = torch.linalg.solve_ex(A, -g)
        delta = torch.where((info == 0)[:, None] & active[:, None], torch.nan_to_num(delta), 0.0)
        new_state = retract(state, delta, frame)
        new_cost, new_aux = evaluate(new_state)
        moved = active & torch.isfinite(new_cost) & (new_cost < cost)
        converged = moved & (cost - new_cost <= tol * cost)
        lam = torch.where(moved, lam * 0.1, lam * 10.0).clamp(1e-12, 1e12)
        active = active & ~converged & (lam < max_lambda) & (cost > 0)
        state, aux = _select(moved, new_state, state), _select(moved, new_aux, aux)
        cost = torch.where(moved, new_cost, cost)
    return state, cost


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
    B = X.shape[0]
    w2 = w.repeat_interleave(2, dim=1).unsqueeze(-1)

    def evaluate(state: Tensors) -> tuple[torch.Tensor, Tensors]:
        r, Xc = reprojection_residuals(state[0], X, x, Kd)
        return (w * (r * r).sum(-1)).sum(-1), (r, Xc)

    def linearise(state: Tensors, aux: Tensors) -> tuple[torch.Tensor, torch.Tensor, Tensors]:
        r, Xc = aux
        # Jacobian of the normalised projection (a, b) = (x/z, y/z) w.r.t. (rho, phi), then through K's 2x2 block
        iz = 1.0 / Xc[..., 2].clamp_min(1e-9)
        a, b = Xc[..., 0] * iz, Xc[..., 1] * iz
        zero = torch.zeros_like(a)
        Ja = torch.stack([iz, zero, -a * iz, -a * b, 1.0 + a * a, -b], -1)
        Jb = torch.stack([zero, iz, -b * iz, -(1.0 + b * b), a * b, a], -1)
        J = torch.stack([Kd[:, None, 0, 0, None] * Ja + Kd[:, None, 0, 1, None] * Jb,
                         Kd[:, None, 1, 1, None] * Jb], -2).reshape(B, -1, 6)  # (B,2N,6)
        wJ = J * w2
        return wJ.transpose(1, 2) @ J, (wJ * r.reshape(B, -1, 1)).sum(1), ()

    def retract(state: Tensors, delta: torch.Tensor, frame: Tensors) -> Tensors:
        T = state[0]
        dR = axis_angle_to_rotation_matrix(delta[:, 3:])
        T_new = T.clone()
        T_new[:, :3, :3] = dR @ T[:, :3, :3]
        T_new[:, :3, 3] = (dR @ T[:, :3, 3:4]).squeeze(-1) + delta[:, :3]
        return (T_new,)

    (T,), cost = levenberg_marquardt((T_init.to(torch.float64).clone(),), evaluate, linearise, retract,
                                     torch.ones(B, dtype=torch.bool, device=X.device), iterations=iterations,
                                     lambda_init=lambda_init, tol=tol, max_lambda=1e4, diagonal_floor=1e-12,
                                     ridge=1e-12)
    return T.to(out_dtype), cost.to(out_dtype)
