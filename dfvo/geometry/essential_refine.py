"""Local optimisation of essential matrices: robust Levenberg-Marquardt of the Sampson error on the essential
manifold, batched over problems.

Convention:
    ``x_i``, ``x_j`` (P,N,2) are normalised camera coordinates (``K^-1 [u, v, 1]``) of matching points in the
    earlier image i and the later image j, ``mask`` (P,N) bool the rows that take part. ``E = [t]_x R`` with
    ``x_j^T E x_i = 0``, where ``(R, t)`` is ``T_cur_prev`` up to scale (frame-i points into camera j,
    ``|t| = 1``). The five parameters are a right perturbation of the rotation, ``R <- R exp([w]_x)``, and a
    step of ``t`` in the tangent plane of the unit sphere, ``t <- normalise(t + a b1 + c b2)`` with
    ``(b1, b2)`` an orthonormal basis of that plane.
    The cost is the Cauchy (Lorentzian) robust sum ``sum_n sigma^2 log(1 + min(r_n^2 / sigma^2, c^2))`` of the
    signed Sampson distances ``r_n`` (normalised units), capped at ``c = cutoff`` so that rows farther than
    ``c sigma`` (outliers) have no influence at all. Each Levenberg-Marquardt step solves the Gauss-Newton system
    with the gradient weights ``rho' = 1 / (1 + z)`` and the curvature weights ``rho' + 2 z rho'' =
    (1 - z) / (1 + z)^2`` (``z = r^2 / sigma^2``; the robust second-order correction of Triggs et al.,
    "Bundle adjustment - a modern synthesis", floored at ``curvature_floor`` so that rows beyond sigma add no
    negative curvature): far faster than plain reweighting when most rows sit near sigma. A step is kept only
    when it lowers the robust cost (the Levenberg-Marquardt core of :mod:`dfvo.geometry.lm`). All arithmetic is
    float64; CPU time goes mostly to per-operation overhead, so the code uses few, large tensor operations.
"""

from __future__ import annotations

import functools

import torch
from kornia.core.check import KORNIA_CHECK, KORNIA_CHECK_SHAPE
from kornia.geometry.epipolar import decompose_essential_matrix

from dfvo.geometry.lm import levenberg_marquardt

__all__ = ["skew", "so3_exp", "essential_from_rt", "refine_essential"]

@functools.lru_cache(maxsize=8)
def _generators(dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """(3,9): ``skew(v).flatten() = v @ G``; row k is the so(3) generator of axis k, flattened."""
    return torch.tensor([[0, 0, 0, 0, 0, -1, 0, 1, 0], [0, 0, 1, 0, 0, 0, -1, 0, 0], [0, -1, 0, 1, 0, 0, 0, 0, 0]],
                        dtype=dtype, device=device)


def skew(v: torch.Tensor) -> torch.Tensor:
    """Cross-product matrices.

    Convention:
        (...,3) -> (...,3,3) with ``skew(v) @ x = v x x``, in the dtype of ``v`` (floating point).
    """
    return (v @ _generators(v.dtype, v.device)).reshape(*v.shape[:-1], 3, 3)


def so3_exp(w: torch.Tensor) -> torch.Tensor:
    """Rotation matrices ``exp([w]_x)`` (Rodrigues) of axis-angle vectors.

    Convention:
        (...,3) radians -> (...,3,3), exact to rounding also for tiny angles (Taylor coefficients there).
    """
    th2 = (w * w).sum(-1, keepdim=True)[..., None]
    th = th2.sqrt()
    small = th2 < 1e-8
    safe = torch.where(small, torch.ones_like(th), th)
    a = torch.where(small, 1.0 - th2 / 6.0, torch.sin(safe) / safe)
    b = torch.where(small, 0.5 - th2 / 24.0, (1.0 - torch.cos(safe)) / (safe * safe))
    W = skew(w)
    return torch.eye(3, dtype=w.dtype, device=w.device) + a * W + b * (W @ W)


def essential_from_rt(R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Essential matrix ``E = [t]_x R`` of a motion ``T_cur_prev = [R | t]``.

    Convention:
        R (...,3,3), t (...,3) -> E (...,3,3). With ``x_j ~ R x_i + t`` (frame-i points into camera j,
        normalised coordinates) ``x_j^T E x_i = 0``.
    """
    return skew(t) @ R


def _tangent_basis(t: torch.Tensor) -> torch.Tensor:
    """(...,2,3): an orthonormal basis (b1, b2) of the plane perpendicular to unit vectors t (...,3).

    Branch-free construction of Duff et al. (2017), "Building an orthonormal basis, revisited".
    """
    x, y, z = t.unbind(-1)
    sign = torch.where(z >= 0, 1.0, -1.0).to(t)
    a = -1.0 / (sign + z)
    b = x * y * a
    b1 = torch.stack([1.0 + sign * x * x * a, sign * b, -sign * x], -1)
    b2 = torch.stack([b, sign + y * y * a, -y], -1)
    return torch.stack([b1, b2], -2)


def _residuals(R: torch.Tensor, t: torch.Tensor, basis: torch.Tensor | None, Xi: torch.Tensor, Xj: torch.Tensor
               ) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Signed Sampson residuals r (P,N) of ``E = [t]_x R`` and, with ``basis`` (P,2,3), their Jacobian (P,5,N).

    ``Xi``, ``Xj`` (P,3,N) are homogeneous normalised points, one column per row. With ``a = E x_i``,
    ``c = E^T x_j``, ``e = x_j . a``, ``d = a_0^2 + a_1^2 + c_0^2 + c_1^2``: ``r = e / sqrt(d)`` and
    ``dr = (de - (e / d) (a_0 da_0 + a_1 da_1 + c_0 dc_0 + c_1 dc_1)) / sqrt(d)`` with ``da = dE x_i``,
    ``dc = dE^T x_j``, ``de = x_j . da``, where ``dE = E [e_k]_x`` for the rotation (``R <- R exp([w]_x)``) and
    ``dE = [b]_x R`` for a tangent step ``b`` of ``t``.
    """
    E = skew(t) @ R
    A = E @ Xi  # (P,3,N): E x_i
    C = E.transpose(-1, -2) @ Xj  # (P,3,N): E^T x_j
    e = (Xj * A).sum(1)
    AC = torch.cat([A[:, :2], C[:, :2]], 1)  # (P,4,N)
    d = AC.square().sum(1).clamp_min(1e-300)
    s = d.sqrt()
    r = e / s
    if basis is None:
        return r, None
    P = R.shape[0]
    dE = torch.cat([E[:, None] @ _generators(E.dtype, E.device).view(1, 3, 3, 3), skew(basis) @ R[:, None]],
                   1)  # (P,5,3,3)
    dA = (dE.reshape(P, 15, 3) @ Xi).view(P, 5, 3, -1)
    dC = (dE.transpose(-1, -2).reshape(P, 15, 3) @ Xj).view(P, 5, 3, -1)
    de = (dA * Xj[:, None]).sum(2)
    dd = (torch.cat([dA[:, :, :2], dC[:, :, :2]], 2) * AC[:, None]).sum(2)
    return r, (de - (e / d)[:, None] * dd) / s[:, None]


def refine_essential(E: torch.Tensor, x_i: torch.Tensor, x_j: torch.Tensor, mask: torch.Tensor,
                     sigma: float | torch.Tensor,
                     iterations: int = 5, lambda_init: float = 1e-4, tol: float = 1e-6,
                     curvature_floor: float = 1e-3, cutoff: float = 3.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Robust local optimisation of essential matrices on their manifold (see the module docstring).

    Args:
        E: (P,3,3) initial essential matrices (any of the four ``(R, t)`` that one encodes is used: all give
            the same Sampson errors). Non-finite ones, and those with fewer than 5 rows, are returned as they
            are, with an infinite cost.
        x_i, x_j: (P,N,2) normalised coordinates in images i (previous) and j (current).
        mask: (P,N) bool rows that take part (e.g. all valid rows: the robust weights handle the outliers).
        sigma: scale of the Cauchy cost in normalised units, one for all or (P,) (e.g. the RANSAC threshold in
            pixels / focal length).
        iterations: maximum Levenberg-Marquardt steps (each problem stops on its own).
        lambda_init: initial damping, relative to the diagonal of the normal matrix.
        tol: relative decrease of the cost below which a problem counts as converged.
        curvature_floor: lower bound of the curvature weights (see the module docstring).
        cutoff: rows farther than ``cutoff * sigma`` from the model have no influence (their cost is capped):
            far outliers do not pull the model, as they would with the plain Cauchy cost.

    Convention:
        Returns E (P,3,3) float64, ``[t]_x R`` with ``|t| = 1`` (singular values 1, 1, 0), and its robust cost
        (P,) float64 in normalised units squared (``inf`` where E was not finite or had fewer than 5 rows).
    """
    KORNIA_CHECK_SHAPE(E, ["P", "3", "3"])
    KORNIA_CHECK_SHAPE(x_i, ["P", "N", "2"])
    KORNIA_CHECK(x_j.shape == x_i.shape and mask.shape == x_i.shape[:2] and E.shape[0] == x_i.shape[0],
                 f"refine_essential: E {tuple(E.shape)}, x_i {tuple(x_i.shape)}, x_j {tuple(x_j.shape)}, "
                 f"mask {tuple(mask.shape)} must share P (and N)")
    sig = torch.as_tensor(sigma, dtype=torch.float64, device=E.device).expand(E.shape[0])
    KORNIA_CHECK(bool((sig > 0).all()), "refine_essential: sigma must be > 0")
    E = E.to(torch.float64)
    P, dev = E.shape[0], E.device
    finite = torch.isfinite(E).all(-1).all(-1)
    R, _, t = decompose_essential_matrix(torch.where(finite[:, None, None], E,
                                                     torch.eye(3, dtype=E.dtype, device=dev)))
    t = t.reshape(P, 3)
    t = t / t.norm(dim=-1, keepdim=True).clamp_min(1e-300)
    xi, xj = x_i.to(torch.float64), x_j.to(torch.float64)
    w = (mask & finite[:, None] & torch.isfinite(xi).all(-1) & torch.isfinite(xj).all(-1)).to(torch.float64)
    ones = torch.ones_like(w[:, None])
    Xi = torch.cat([torch.nan_to_num(xi).transpose(1, 2), ones], 1)  # (P,3,N)
    Xj = torch.cat([torch.nan_to_num(xj).transpose(1, 2), ones], 1)
    s2 = sig.square()[:, None]
    c2 = float(cutoff) ** 2

    def cost_of(r: torch.Tensor) -> torch.Tensor:
        return (w * torch.log1p((r * r / s2).clamp(max=c2))).sum(-1) * s2[:, 0]

    def normal_equations(R_: torch.Tensor, t_: torch.Tensor, basis: torch.Tensor
                         ) -> tuple[torch.Tensor, torch.Tensor]:
        """Gauss-Newton matrix (P,5,5) and gradient (P,5) of the robust cost at (R_, t_)."""
        r, J = _residuals(R_, t_, basis, Xi, Xj)
        z = r * r / s2
        wi = torch.where(z < c2, w, 0.0)  # rows beyond the cutoff have no influence
        wg = wi / (1.0 + z)
        wh = wi * ((1.0 - z) / (1.0 + z).square()).clamp_min(curvature_floor)
        return (J * wh[:, None]) @ J.transpose(1, 2), ((J * wg[:, None]) @ r[..., None])[..., 0]

    def evaluate(state: tuple[torch.Tensor, ...]) -> tuple[torch.Tensor, tuple[torch.Tensor, ...]]:
        return cost_of(_residuals(state[0], state[1], None, Xi, Xj)[0]), ()

    def linearise(state: tuple[torch.Tensor, ...], aux: tuple[torch.Tensor, ...]
                  ) -> tuple[torch.Tensor, torch.Tensor, tuple[torch.Tensor, ...]]:
        basis = _tangent_basis(state[1])
        H, g = normal_equations(state[0], state[1], basis)
        return H, g, (basis,)

    def retract(state: tuple[torch.Tensor, ...], delta: torch.Tensor, frame: tuple[torch.Tensor, ...]
                ) -> tuple[torch.Tensor, ...]:
        R_new = state[0] @ so3_exp(delta[:, :3])
        t_new = state[1] + (delta[:, 3:, None] * frame[0]).sum(1)
        return R_new, t_new / t_new.norm(dim=-1, keepdim=True).clamp_min(1e-300)

    (R, t), cost = levenberg_marquardt((R, t), evaluate, linearise, retract, finite & (w.sum(-1) >= 5),
                                       iterations=iterations, lambda_init=lambda_init, tol=tol, max_lambda=1e6,
                                       diagonal_floor=1e-300, ridge=1e-300)
    ok = finite & (w.sum(-1) >= 5)
    return (torch.where(ok[:, None, None], essential_from_rt(R, t), E),
            torch.where(ok, cost, torch.full_like(cost, float("inf"))))
