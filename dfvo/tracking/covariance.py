"""Covariance of each frame's relative motion: what a fusion filter (an EKF fusing wheel odometry or an IMU) needs.

Convention: :mod:`dfvo.geometry.pose_covariance` (the error 6-vector ``[phi, dt]`` of ``T_prev_cur`` in the previous
    camera's axes, its NEES, propagation, ROS order and the ``frames.csv`` columns).

Where each frame's covariance comes from (:func:`step_covariance`):
    - ``E`` (essential matrix + scale): rotation and translation direction from the normal equations of the Sampson
      residuals of the inliers at the solution, ``C5 = sigma^2 (J^T J)^-1`` over the five parameters of (R, unit t)
      (:func:`essential_normal_covariance`; the Jacobian is computed here, independently of the local optimisation's
      own code). ``sigma`` is estimated from the inliers' residuals, corrected for the truncation at the inlier
      threshold (:func:`truncated_sigma`: a Gaussian cut at ``c`` has a smaller spread than its own sigma). The
      length: ``log |t|`` has the variance of the scale filter's posterior (``ScaleEstimate.state.pxx``), or
      ``tracker.scale_filter.cnn_log_std**2`` when no filter runs (the filter's one-observation variance).
    - ``PnP``: the normal equations of the reprojection residuals of PnP's inliers (left perturbation of
      ``T_cur_prev``), sigma from the residuals as above (2-D truncation), plus the depth network's scale uncertainty
      (a global depth factor ``lambda`` scales PnP's translation by ``lambda`` exactly; ``log lambda`` has the
      variance ``cnn_log_std**2``).
    - ``constant_motion`` (and frames whose normal equations are singular): a large diagonal
      (``tracker.covariance.constant_motion_rot_std`` rad, ``constant_motion_trans_std`` m or the step's length if
      larger): a filter fusing it learns next to nothing from the frame.
    The normal equations' part (pixel noise) is multiplied by ``tracker.covariance.inflation``: 1 is the model's
    own, calibrated on the synthetic world with independent pixel noise; real flow errors are correlated between
    neighbouring pixels, which the normal equations cannot see (``docs/robots.md``: the factor KITTI needs). For the
    same reason the correlation between the rotation and the translation errors that the normal equations give is
    dropped unless ``tracker.covariance.correlated`` (measured: real steps do not follow it; the blocks do).
"""

from __future__ import annotations

import math

import torch

from dfvo.geometry.essential_refine import skew
from dfvo.geometry.pose_covariance import antisymmetric_vee, symmetric

__all__ = ["step_covariance", "essential_normal_covariance", "essential_step_covariance", "pnp_step_covariance",
           "length_log_variance", "constant_motion_covariance", "truncated_sigma", "uncorrelated"]

MIN_INLIERS = 8


# ---------------------------------------------------------------------------------------------------- small helpers
def _tangent_basis(t: torch.Tensor) -> torch.Tensor:
    """(2,3) orthonormal basis of the plane perpendicular to the unit vector ``t`` (3,)."""
    helper = torch.zeros_like(t)
    helper[int(torch.argmin(t.abs()))] = 1.0
    b1 = torch.linalg.cross(t, helper)
    b1 = b1 / b1.norm()
    return torch.stack([b1, torch.linalg.cross(t, b1)])


def _normalised(pts: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """(N,2) pixels -> (N,3) homogeneous normalised coordinates ``K^-1 [u, v, 1]``."""
    ones = torch.ones_like(pts[:, :1])
    return torch.cat([pts, ones], -1) @ torch.linalg.inv(K).T


def _jacobian(f: object, n: int, h: float = 1e-6) -> torch.Tensor:
    """(M,n) Jacobian at 0 of ``f``: (B,n) float64 -> (B,M) (batched over parameter vectors), by central
    differences in one batched call. The functions differentiated here are smooth and O(1)-scaled in float64, so the
    truncation (~h^2) and rounding (~1e-16/h) errors are ~1e-10 relative; far cheaper than autograd's forward mode
    (which also costs seconds on its first call)."""
    steps = torch.eye(n, dtype=torch.float64) * h
    out = f(torch.cat([steps, -steps]))
    return ((out[:n] - out[n:]) / (2.0 * h)).T


def _inv_sym(A: torch.Tensor) -> torch.Tensor | None:
    """Inverse of a symmetric positive definite matrix, or None when it is (numerically) singular."""
    if not bool(torch.isfinite(A).all()):
        return None
    evals = torch.linalg.eigvalsh(A)
    if not float(evals[0]) > 1e-12 * max(float(evals[-1]), 1e-300):
        return None
    return torch.cholesky_inverse(torch.linalg.cholesky(A))


def truncated_sigma(residuals: torch.Tensor, cutoff: float, dof: int, dims: int = 1, max_ratio: float = 10.0
                    ) -> float:
    """The standard deviation (per coordinate) of zero-mean Gaussian residuals seen only within ``cutoff``.

    Inliers are the residuals inside the threshold, so their spread underestimates the noise: a Gaussian of std
    sigma cut at ``c = k sigma`` has ``E[r^2 | |r| < c] = sigma^2 (1 - 2 k phi(k) / (2 Phi(k) - 1))`` (one
    coordinate, ``dims=1``) or ``2 sigma^2 (1 - (k^2/2) e^(-k^2/2) / (1 - e^(-k^2/2)))`` (the squared norm of a 2-D
    residual, ``dims=2``). The observed mean square (sum over ``dof`` degrees of freedom) is matched by bisection.

    Args:
        residuals: (N,) one-coordinate residuals (``dims=1``) or (N,2) (``dims=2``), all within ``cutoff``.
        cutoff: the inlier threshold (in the residuals' unit). dof: degrees of freedom left (N*dims - parameters).
        max_ratio: the answer is at most ``max_ratio * cutoff`` (residuals spread evenly up to the threshold say
            only that the noise is not small).

    Returns:
        sigma per coordinate, in the residuals' unit.
    """
    mean_sq = float(residuals.square().sum()) / max(int(dof), 1) * dims  # E[|r|^2] per residual (dims coordinates)
    if not mean_sq > 0:
        return 0.0

    def truncated_mean_sq(sigma: float) -> float:
        k = cutoff / sigma
        if dims == 1:
            mass = math.erf(k / math.sqrt(2.0))
            pdf = math.exp(-0.5 * k * k) / math.sqrt(2.0 * math.pi)
            return sigma * sigma * (1.0 - 2.0 * k * pdf / max(mass, 1e-300))
        q = math.exp(-0.5 * k * k)
        return 2.0 * sigma * sigma * (1.0 - 0.5 * k * k * q / max(1.0 - q, 1e-300))

    lo, hi = 1e-9 * cutoff, max_ratio * cutoff
    if truncated_mean_sq(hi) <= mean_sq:
        return hi
    for _ in range(100):  # bisection in log space; the truncated mean square grows with sigma
        mid = math.sqrt(lo * hi)
        if truncated_mean_sq(mid) < mean_sq:
            lo = mid
        else:
            hi = mid
    return math.sqrt(lo * hi)


# ---------------------------------------------------------------------------------------------------- E frames
def _sampson(E: torch.Tensor, Xi: torch.Tensor, Xj: torch.Tensor) -> torch.Tensor:
    """Signed Sampson distances (...,N) of homogeneous normalised points (N,3) to ``x_j^T E x_i = 0``, E (...,3,3)."""
    a = Xi @ E.transpose(-1, -2)  # E x_i
    c = Xj @ E  # E^T x_j
    e = (Xj * a).sum(-1)
    return e / (a[..., 0] ** 2 + a[..., 1] ** 2 + c[..., 0] ** 2 + c[..., 1] ** 2).clamp_min(1e-300).sqrt()


def essential_normal_covariance(R: torch.Tensor, t: torch.Tensor, pts_prev: torch.Tensor, pts_cur: torch.Tensor,
                                K: torch.Tensor, threshold_px: float) -> tuple[torch.Tensor, torch.Tensor, int,
                                                                                 float] | None:
    """Covariance of (R, unit t) of ``T_cur_prev`` from the normal equations of the inliers' Sampson residuals.

    The five parameters are ``R <- R (I + [w]_x)`` (w: 3, rad) and ``t <- normalise(t + a b1 + c b2)`` with
    ``(b1, b2)`` the rows of the returned basis.

    Args:
        R: (3,3), t: (3,) unit translation of ``T_cur_prev`` (frame-i points into camera j).
        pts_prev, pts_cur: (N,2) pixels of the selected rows in images i and j. K: (3,3).
        threshold_px: inlier threshold in pixels (divided by the mean focal length, as the RANSAC does).

    Returns:
        (C5 (5,5) float64, basis (2,3), number of inliers, sigma in pixels) or None (too few inliers, singular
        normal equations).
    """
    R, t, K = R.to(torch.float64), t.to(torch.float64), K.to(torch.float64)
    Xi, Xj = _normalised(pts_prev.to(torch.float64), K), _normalised(pts_cur.to(torch.float64), K)
    focal = 0.5 * float(K[0, 0] + K[1, 1])
    thr = threshold_px / focal
    r0 = _sampson(skew(t) @ R, Xi, Xj)  # (N,)
    inl = torch.isfinite(r0) & (r0.abs() < thr)
    n = int(inl.sum())
    if n < MIN_INLIERS:
        return None
    Xi, Xj, r0 = Xi[inl], Xj[inl], r0[inl]
    basis = _tangent_basis(t)

    def residuals(p: torch.Tensor) -> torch.Tensor:  # (B,5) -> (B,n)
        Rp = R @ (torch.eye(3, dtype=p.dtype) + skew(p[:, :3]))
        tp = t + p[:, 3:4] * basis[0] + p[:, 4:5] * basis[1]
        tp = tp / tp.norm(dim=-1, keepdim=True)
        return _sampson(skew(tp) @ Rp, Xi, Xj)

    J = _jacobian(residuals, 5)  # (n,5)
    info = _inv_sym(J.T @ J)
    if info is None:
        return None
    sigma = truncated_sigma(r0, thr, n - 5)
    return sigma * sigma * info, basis, n, sigma * focal


def essential_step_covariance(T_cur_prev: torch.Tensor, pts_prev: torch.Tensor, pts_cur: torch.Tensor,
                              K: torch.Tensor, threshold_px: float, log_length_var: float,
                              inflation: float = 1.0) -> torch.Tensor | None:
    """6x6 covariance of ``T_prev_cur`` (module convention) of an E-tracked frame.

    Args:
        T_cur_prev: (4,4) the metric pose the tracker gave (``[R | s t]``).
        pts_prev, pts_cur: (N,2) pixels of the selected rows. K: (3,3). threshold_px: the E inlier threshold.
        log_length_var: variance of ``log s`` (the scale filter's posterior).
        inflation: factor on the normal equations' covariance of (R, unit t) (not on the length's variance).

    Returns:
        (6,6) float64, or None when the normal equations cannot be solved.
    """
    T = T_cur_prev.to(torch.float64)
    R0, tm = T[:3, :3], T[:3, 3]
    s0 = float(tm.norm())
    if not s0 > 0:
        return None
    normal = essential_normal_covariance(R0, tm / s0, pts_prev, pts_cur, K, threshold_px)
    if normal is None:
        return None
    C5, basis, _, _ = normal
    t0 = tm / s0
    Cp = torch.zeros(6, 6, dtype=torch.float64)
    Cp[:5, :5] = C5 * inflation
    Cp[5, 5] = float(log_length_var)
    R_pc0, t_pc0 = R0.T, -R0.T @ tm

    def step(p: torch.Tensor) -> torch.Tensor:  # (B,6) parameters -> (B,6) error of T_prev_cur (module convention)
        R = R0 @ (torch.eye(3, dtype=p.dtype) + skew(p[:, :3]))
        u = t0 + p[:, 3:4] * basis[0] + p[:, 4:5] * basis[1]
        t = s0 * torch.exp(p[:, 5:6]) * u / u.norm(dim=-1, keepdim=True)
        R_pc = R.transpose(-1, -2)
        t_pc = -(R_pc @ t[..., None])[..., 0]
        return torch.cat([antisymmetric_vee(R_pc @ R_pc0.T), t_pc - t_pc0], -1)

    G = _jacobian(step, 6)
    return symmetric(G @ Cp @ G.T)


# ---------------------------------------------------------------------------------------------------- PnP frames
def _project(T: torch.Tensor, X: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Pixels (...,N,2) of points X (N,3) under poses T (...,4,4) (``T_cur_prev``) and intrinsics K (3,3)."""
    Xc = X @ T[..., :3, :3].transpose(-1, -2) + T[..., None, :3, 3]
    return (Xc[..., :2] / Xc[..., 2:3]) @ K[:2, :2].T + K[:2, 2]


def pnp_step_covariance(T_cur_prev: torch.Tensor, points_prev: torch.Tensor, pixels_cur: torch.Tensor,
                        K: torch.Tensor, threshold_px: float, depth_log_var: float,
                        inflation: float = 1.0, backwards: bool = False) -> torch.Tensor | None:
    """6x6 covariance of ``T_prev_cur`` (module convention) of a PnP-tracked frame.

    Args:
        T_cur_prev: (4,4) PnP's pose. points_prev: (N,3) the previous frame's points (its depth, back-projected),
            pixels_cur: (N,2) their observations in the current image. K: (3,3).
        threshold_px: PnP's inlier threshold (reprojection error, pixels).
        depth_log_var: variance of the log of the depth's global scale (PnP's translation scales with it).
        inflation: factor on the normal equations' covariance (not on the depth scale's variance).
        backwards: PnP ran the other way (the earlier frame had no depth): the arguments are then ``T_prev_cur``,
            the current frame's points and their pixels in the previous image, and the pose itself is the step.

    Returns:
        (6,6) float64, or None (too few inliers, singular normal equations).
    """
    T0, K = T_cur_prev.to(torch.float64), K.to(torch.float64)
    X, x = points_prev.to(torch.float64), pixels_cur.to(torch.float64)
    res0 = _project(T0, X, K) - x
    depth_ok = (X @ T0[:3, :3].T + T0[:3, 3])[:, 2] > 1e-9
    inl = depth_ok & torch.isfinite(res0).all(-1) & (res0.square().sum(-1) < threshold_px ** 2)
    n = int(inl.sum())
    if n < MIN_INLIERS:
        return None
    X, x, res0 = X[inl], x[inl], res0[inl]
    R0, t0 = T0[:3, :3], T0[:3, 3]

    def perturbed(p: torch.Tensor) -> torch.Tensor:  # (B,>=6) [rho, phi, ...] -> (B,4,4): left perturbation
        dR = torch.eye(3, dtype=p.dtype) + skew(p[:, 3:6])
        T = torch.eye(4, dtype=p.dtype).repeat(p.shape[0], 1, 1)
        T[:, :3, :3] = dR @ R0
        T[:, :3, 3] = (dR @ t0[:, None])[..., 0] + p[:, :3]
        return T

    J = _jacobian(lambda p: (_project(perturbed(p), X, K) - x).reshape(p.shape[0], -1), 6)  # (2n,6)
    info = _inv_sym(J.T @ J)
    if info is None:
        return None
    sigma = truncated_sigma(res0, threshold_px, 2 * n - 6, dims=2)
    Cp = torch.zeros(7, 7, dtype=torch.float64)
    Cp[:6, :6] = sigma * sigma * info * inflation
    Cp[6, 6] = float(depth_log_var)
    R_pc0, t_pc0 = R0.T, -R0.T @ t0

    if backwards:  # the solved pose is the step T_prev_cur itself
        R_pc0, t_pc0 = R0, t0

    def step(p: torch.Tensor) -> torch.Tensor:  # (B,7) -> (B,6)
        T = perturbed(p)
        if backwards:
            R_pc, t_pc = T[:, :3, :3], T[:, :3, 3] * torch.exp(p[:, 6:7])
        else:
            R_pc = T[:, :3, :3].transpose(-1, -2)
            t_pc = -(R_pc @ (T[:, :3, 3] * torch.exp(p[:, 6:7]))[..., None])[..., 0]
        return torch.cat([antisymmetric_vee(R_pc @ R_pc0.T), t_pc - t_pc0], -1)

    G = _jacobian(step, 7)
    return symmetric(G @ Cp @ G.T)


# ---------------------------------------------------------------------------------------------------- every frame
def constant_motion_covariance(T_prev_cur: torch.Tensor, cfg: object) -> torch.Tensor:
    """The large diagonal of a frame without a measurement (``cfg``: a
    :class:`~dfvo.tracking.config.CovarianceConfig`)."""
    trans = max(cfg.constant_motion_trans_std, float(T_prev_cur[:3, 3].norm()))
    return torch.diag(torch.tensor([cfg.constant_motion_rot_std ** 2] * 3 + [trans ** 2] * 3, dtype=torch.float64))


def step_covariance(tracker: str | None, T_cur_prev: torch.Tensor | None, T_prev_cur: torch.Tensor,
                    pts_prev: torch.Tensor, pts_cur: torch.Tensor, K: torch.Tensor, depth_prev: torch.Tensor,
                    cfg: object, log_length_var: float, depth_cur: torch.Tensor | None = None) -> torch.Tensor:
    """The 6x6 covariance (module convention) of one frame's ``T_prev_cur``, whichever tracker gave it.

    Args:
        tracker: the frame's :class:`~dfvo.tracking.diagnostics.TrackerUsed` value (``E``, ``PnP``,
            ``constant_motion``). T_cur_prev: (4,4) the tracker's pose (None for constant motion).
        T_prev_cur: (4,4) the step used. pts_prev, pts_cur: (N,2) pixels of the selected rows.
        K: (3,3). depth_prev: (1,1,H,W) the earlier frame's depth (PnP's 3-D points).
        cfg: the :class:`~dfvo.tracking.config.TrackerConfig`.
        log_length_var: variance of log(length) of an E frame (the scale filter's).
        depth_cur: (1,1,H,W) the later frame's depth when PnP ran backwards (the earlier frame had none).

    Returns:
        (6,6) float64; a frame whose normal equations fail gets the constant-motion value.
    """
    from dfvo.geometry.camera import backproject_points
    from dfvo.tracking.scale import sample_depth

    ccfg = cfg.covariance
    cov = None
    if tracker == "E" and T_cur_prev is not None:
        cov = essential_step_covariance(T_cur_prev, pts_prev, pts_cur, K, cfg.essential.threshold_px, log_length_var,
                                        ccfg.inflation)
    elif tracker == "PnP" and T_cur_prev is not None:
        backwards = depth_cur is not None
        lifted, seen = (pts_cur, pts_prev) if backwards else (pts_prev, pts_cur)
        z, ok = sample_depth(depth_cur if backwards else depth_prev, lifted[None], cfg.scale.max_depth,
                             cfg.scale.depth_crop_top)
        ok = ok[0]
        X = backproject_points(lifted[None].to(torch.float64), z, K[None].to(torch.float64))[0]
        cov = pnp_step_covariance(T_prev_cur if backwards else T_cur_prev, X[ok], seen[ok], K, cfg.pnp.threshold_px,
                                  cfg.scale_filter.cnn_log_std ** 2, ccfg.inflation, backwards=backwards)
    if cov is None or not bool(torch.isfinite(cov).all()):
        return constant_motion_covariance(T_prev_cur, ccfg)
    return cov if ccfg.correlated else uncorrelated(cov)


def uncorrelated(cov: torch.Tensor) -> torch.Tensor:
    """A copy of a (6,6) step covariance with its rotation-translation cross blocks zeroed (the blocks alone:
    ``tracker.covariance.correlated=false``)."""
    cov = cov.clone()
    cov[:3, 3:] = 0.0
    cov[3:, :3] = 0.0
    return cov


def length_log_variance(estimate: object | None, prior_pxx: float, length: float, cfg: object) -> float:
    """Variance of log(length) of an E frame's translation.

    Args:
        estimate: the frame's :class:`~dfvo.tracking.scale_filter.ScaleEstimate` (None: no filter runs; the CNN-depth
            scale alone, whose one-observation variance is ``cfg.scale_filter.cnn_log_std**2``).
        prior_pxx: the filter's prior variance this frame (used when a gate replaced the fused length by the
            prediction). length: the length used (m). cfg: the tracker config.
    """
    if estimate is None or estimate.scale is None:
        return float(cfg.scale_filter.cnn_log_std) ** 2
    if abs(float(estimate.scale) - length) <= 1e-9 * max(1.0, length):
        return float(estimate.state.pxx)
    return float(prior_pxx)


