"""Two-view geometry on padded, batched correspondences: essential and homography RANSAC (with local
optimisation), decomposition with cheirality, closed-form two-view depths, Sampson and homography residuals.

Convention:
    ``pts_i`` (B,N,2) are pixels in image i (the previous frame), ``pts_j`` (B,N,2) the matching pixels in
    image j (the current frame); ``mask`` (B,N) bool marks the real rows of the padding. ``K`` (B,3,3) are
    the intrinsics (same camera for both images). The essential matrix satisfies ``x_j^T E x_i = 0`` on
    normalised coordinates ``x = K^-1 [u, v, 1]^T``, and its decomposition ``(R, t)`` is ``T_cur_prev``: it
    maps frame-i (previous) points into camera j (current), ``t`` has unit norm. Invert it to get
    ``T_prev_cur``.

Randomness: each frame of the batch draws from its own ``torch.Generator`` (a list, one per frame), so a
frame's result depends neither on the other frames of its batch nor on its padding (see
:mod:`dfvo.geometry.ransac`).

Everything runs in float64 internally (the five-point solver of kornia is float64 anyway), except the
float32 ranking of essential-matrix candidates on a row subset.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from kornia.core.check import KORNIA_CHECK, KORNIA_CHECK_SHAPE
from kornia.geometry.epipolar import decompose_essential_matrix, find_essential
from kornia.geometry.homography import find_homography_dlt

from dfvo.geometry.essential_refine import refine_essential
from dfvo.geometry.ransac import hypothesise_and_verify, pick_best, rank_models, score_models
from dfvo.validation import check

__all__ = ["EssentialConfig", "TwoViewResult", "normalise_points", "normalised_rays", "sampson_sq",
           "homography_error_sq", "find_essential_ransac", "find_homography_ransac", "decompose_essential",
           "ray_depths"]


@dataclass
class EssentialConfig:
    """Essential-matrix RANSAC and its validity rules (``tracker.essential`` of
    :class:`dfvo.tracking.config.TrackerConfig`; the RANSAC defaults of :func:`find_essential_ransac`).

    Attributes:
        threshold_px: RANSAC inlier threshold in pixels (converted to normalised coordinates).
        iterations: minimal samples per RANSAC repeat; repeats: repeats, the most inliers wins.
        min_correspondences: with this many or fewer valid correspondences E is invalid.
        min_cheirality_fraction: E is invalid when fewer rows pass cheirality.
    """

    threshold_px: float = 0.2
    iterations: int = 20
    repeats: int = 5
    min_correspondences: int = 10
    min_cheirality_fraction: float = 0.1

    def __post_init__(self) -> None:
        check(self.threshold_px > 0, f"tracker.essential.threshold_px={self.threshold_px}; expected > 0")
        check(int(self.iterations) > 0 and int(self.repeats) > 0,
               f"tracker.essential: iterations={self.iterations}, repeats={self.repeats}; expected positive integers")


@dataclass
class TwoViewResult:
    """Result of :func:`find_essential_ransac` / :func:`find_homography_ransac`.

    Convention:
        i is the previous image, j the current one; E satisfies ``x_j^T E x_i = 0`` (normalised coordinates),
        H maps pixels ``x_j ~ H x_i``.

    Attributes:
        model: (B,3,3) essential matrix (normalised coordinates) or homography (pixels, ``x_j ~ H x_i``).
        inliers: (B,N) bool rows within the threshold of ``model``.
        num_inliers: (B,) long.
        success: (B,) bool, a model was found from enough rows.
    """

    model: torch.Tensor
    inliers: torch.Tensor
    num_inliers: torch.Tensor
    success: torch.Tensor


def _check(pts_i: torch.Tensor, pts_j: torch.Tensor, mask: torch.Tensor, K: torch.Tensor | None, name: str) -> None:
    KORNIA_CHECK_SHAPE(pts_i, ["B", "N", "2"])
    KORNIA_CHECK_SHAPE(pts_j, ["B", "N", "2"])
    KORNIA_CHECK_SHAPE(mask, ["B", "N"])
    ok = pts_j.shape == pts_i.shape and mask.shape == pts_i.shape[:2]
    if K is not None:
        KORNIA_CHECK_SHAPE(K, ["B", "3", "3"])
        ok = ok and K.shape[0] == pts_i.shape[0]
    KORNIA_CHECK(ok, f"{name}: pts_i {tuple(pts_i.shape)}, pts_j {tuple(pts_j.shape)}, mask {tuple(mask.shape)}"
                     f"{'' if K is None else f', K {tuple(K.shape)}'} must share (B,N)")


def normalise_points(pts: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Pixels to normalised camera coordinates ``K^-1 [u, v, 1]``.

    Convention:
        pts (B,N,2) pixels, K (B,3,3) their intrinsics (skew allowed) -> (B,N,2) in the dtype of ``pts``.
    """
    Kd = K.to(pts.dtype)
    x = (pts[..., 0] - Kd[:, None, 0, 2] - Kd[:, None, 0, 1] * (pts[..., 1] - Kd[:, None, 1, 2]) / Kd[:, None, 1, 1])
    return torch.stack([x / Kd[:, None, 0, 0], (pts[..., 1] - Kd[:, None, 1, 2]) / Kd[:, None, 1, 1]], -1)


def normalised_rays(pts: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Viewing rays ``K^-1 [u, v, 1]`` (z = 1) of pixels: pts (B,N,2), K (B,3,3) -> (B,N,3) float64."""
    x = normalise_points(pts.to(torch.float64), K.to(torch.float64))
    return torch.cat([x, torch.ones_like(x[..., :1])], -1)


def sampson_sq(F: torch.Tensor, x_i: torch.Tensor, x_j: torch.Tensor) -> torch.Tensor:
    """Squared Sampson distance of (B,N,2) points to (B,M,3,3) epipolar matrices -> (B,M,N).

    Convention:
        ``x_j^T F x_i = 0`` with ``x_i`` in image i (previous) and ``x_j`` in image j (current). With
        ``F = K^-T E K^-1`` and pixel coordinates this is the squared Sampson distance in pixels (GRIC's
        residual for E); with ``E`` and normalised coordinates it is the normalised one (RANSAC's test).
        Computed in the dtype of the inputs.
    """
    B, M = F.shape[:2]
    N = x_i.shape[1]
    hi = torch.cat([x_i, torch.ones_like(x_i[..., :1])], -1).transpose(1, 2)  # (B,3,N)
    hj = torch.cat([x_j, torch.ones_like(x_j[..., :1])], -1).transpose(1, 2)
    Fx = (F.reshape(B, M * 3, 3) @ hi).view(B, M, 3, N)  # F x_i, one GEMM per frame
    Ftx = (F.transpose(-1, -2).reshape(B, M * 3, 3) @ hj).view(B, M, 3, N)  # F^T x_j
    num = (Ftx[:, :, 0] * x_i[:, None, :, 0] + Ftx[:, :, 1] * x_i[:, None, :, 1] + Ftx[:, :, 2]) ** 2
    den = Fx[:, :, 0] ** 2 + Fx[:, :, 1] ** 2 + Ftx[:, :, 0] ** 2 + Ftx[:, :, 1] ** 2
    return num / den.clamp_min(1e-30)


def homography_error_sq(H: torch.Tensor, x_i: torch.Tensor, x_j: torch.Tensor) -> torch.Tensor:
    """Torr's first-order geometric transfer error (squared, pixels) of (B,N,2) pairs under (B,M,3,3) H -> (B,M,N).

    The two algebraic residuals ``e`` of ``x_j x (H x_i) = 0`` are weighted by ``(J J^T)^-1`` with ``J`` their
    Jacobian with respect to both points: the Sampson approximation of the reprojection error in both images.

    Convention:
        ``x_j ~ H x_i``: ``x_i`` pixels in image i (previous), ``x_j`` in image j (current).
    """
    u1, v1 = x_i[:, None, :, 0], x_i[:, None, :, 1]
    u2, v2 = x_j[:, None, :, 0], x_j[:, None, :, 1]
    h = [H[:, :, r, None, 0] * u1 + H[:, :, r, None, 1] * v1 + H[:, :, r, None, 2] for r in range(3)]
    e1 = v2 * h[2] - h[1]
    e2 = h[0] - u2 * h[2]
    Hm = [[H[:, :, r, c, None] for c in range(3)] for r in range(3)]
    # J rows: d e / d (u1, v1, u2, v2)
    a = (v2 * Hm[2][0] - Hm[1][0], v2 * Hm[2][1] - Hm[1][1], torch.zeros_like(u2), h[2])
    b = (Hm[0][0] - u2 * Hm[2][0], Hm[0][1] - u2 * Hm[2][1], -h[2], torch.zeros_like(u2))
    s11 = sum(x * x for x in a)
    s22 = sum(x * x for x in b)
    s12 = sum(x * y for x, y in zip(a, b, strict=True))
    det = (s11 * s22 - s12 * s12).clamp_min(1e-30)
    return (s22 * e1 * e1 - 2 * s12 * e1 * e2 + s11 * e2 * e2) / det


def _fail(B: int, N: int, eye: bool, device: torch.device) -> TwoViewResult:
    model = torch.eye(3, dtype=torch.float64, device=device).repeat(B, 1, 1) if eye else \
        torch.zeros(B, 3, 3, dtype=torch.float64, device=device)
    z = torch.zeros(B, N, dtype=torch.bool, device=device)
    return TwoViewResult(model, z, z.sum(-1), z.any(-1))


def _gather_rows(x: torch.Tensor, rows: torch.Tensor | None) -> torch.Tensor:
    """x (B,N,2), rows (B,...) long or None -> (B,...,2)."""
    if rows is None:
        return x
    return x.gather(1, rows.reshape(rows.shape[0], -1, 1).expand(-1, -1, 2)).view(*rows.shape, 2)


def find_essential_ransac(pts_i: torch.Tensor, pts_j: torch.Tensor, mask: torch.Tensor, K: torch.Tensor,
                          threshold_px: float = EssentialConfig.threshold_px,
                          iterations: int = EssentialConfig.iterations, repeats: int = EssentialConfig.repeats,
                          generators: list[torch.Generator] | None = None, refine: bool = True,
                          preview: int = 256, max_real: int = 6, refine_iterations: int = 5,
                          refine_starts: int = 2) -> TwoViewResult:
    """Essential matrix by batched five-point RANSAC (kornia ``find_essential``) with a local optimisation.

    Runs :func:`dfvo.geometry.ransac.hypothesise_and_verify`: ``repeats`` repeats of ``iterations`` minimal
    samples, candidates ranked on ``preview`` random rows, each repeat's winner scored on all rows. With
    ``refine`` (local optimisation, LO-RANSAC style) the ``refine_starts`` best repeat winners are each refined
    by :func:`dfvo.geometry.essential_refine.refine_essential` (robust Levenberg-Marquardt of the Sampson error
    of all valid rows over (R, t) on the essential manifold; Cauchy kernel of scale = the threshold, or less
    when the start's residuals are cleaner, cut off at 3 scales, so the inliers are re-weighted at every step)
    and the best refined model wins; without it the best repeat winner wins (best:
    most inliers, then lowest truncated error). A row is an inlier when its normalised Sampson distance is
    below ``threshold_px / f`` (f the mean focal length, the largest of the batch: frames of one sequence
    share K).

    Args:
        pts_i, pts_j: (B,N,2) pixels in images i (previous) and j (current).
        mask: (B,N) bool valid rows.
        K: (B,3,3) intrinsics.
        threshold_px: inlier threshold in pixels (official 0.2).
        iterations: minimal samples per repeat.
        repeats: independent repeats (official 5).
        generators: one ``torch.Generator`` per frame for reproducible sampling (None: global RNG).
        refine: locally optimise the best repeat winners.
        preview: rows (random, per frame, with replacement) on which all candidates are ranked (float32).
        max_real: real five-point candidates kept per sample (of kornia's ten slots).
        refine_iterations: maximum Levenberg-Marquardt steps of the local optimisation.
        refine_starts: how many repeat winners (best first) are refined; more is more robust on hard frames
            (small baselines, many outliers) and costs more.

    Convention:
        ``x_j^T E x_i = 0`` on normalised coordinates; ``decompose_essential(E, ...)`` gives ``T_cur_prev``.

    Returns:
        :class:`TwoViewResult` with ``model`` = E (B,3,3) float64; ``success`` False with fewer than 5 rows.
    """
    _check(pts_i, pts_j, mask, K, "find_essential_ransac")
    KORNIA_CHECK(threshold_px > 0 and iterations > 0 and repeats > 0,
                 f"find_essential_ransac: need threshold_px, iterations, repeats > 0; got {threshold_px}, "
                 f"{iterations}, {repeats}")
    B, N = mask.shape
    enough = mask.sum(-1) >= 5
    if N < 5 or not bool(enough.any()):
        return _fail(B, N, False, pts_i.device)
    Kd = K.to(torch.float64)
    m = mask & enough[:, None]
    xi = torch.where(m[..., None], normalise_points(pts_i.to(torch.float64), Kd), 0.0)
    xj = torch.where(m[..., None], normalise_points(pts_j.to(torch.float64), Kd), 0.0)
    thr = float((threshold_px / (0.5 * (Kd[:, 0, 0] + Kd[:, 1, 1]))).max())
    thr_sq = thr * thr

    def solve(rows: torch.Tensor) -> torch.Tensor:
        S = rows.shape[1]
        cand = find_essential(_gather_rows(xi, rows).view(B * S, 5, 2),
                              _gather_rows(xj, rows).view(B * S, 5, 2)).view(B, S, 10, 3, 3)
        # complex roots come back as NaN slots: keep the first ``max_real`` real ones (five-point samples
        # rarely have more than six real solutions), which cuts the scoring work
        finite = torch.isfinite(cand).all(-1).all(-1)
        order = torch.sort((~finite).to(torch.uint8), dim=-1, stable=True).indices[..., :max_real]
        return cand.gather(2, order[..., None, None].expand(-1, -1, -1, 3, 3))

    def residual(models: torch.Tensor, rows: torch.Tensor | None, exact: bool) -> torch.Tensor:
        a, b = _gather_rows(xi, rows), _gather_rows(xj, rows)
        return sampson_sq(models, a, b) if exact else sampson_sq(models.float(), a.float(), b.float())

    win = hypothesise_and_verify(m, 5, solve, residual, thr_sq, iterations, repeats, generators, preview)
    models, err = win.models, win.err_sq
    if refine:  # local optimisation of the best ``refine_starts`` repeat winners; the best refined one wins
        k = min(max(int(refine_starts), 1), repeats)
        count, trunc = score_models(err, thr_sq, m)
        order = rank_models(count, trunc, thr_sq, N)[:, :k]
        start = models.gather(1, order[..., None, None].expand(-1, -1, 3, 3)).reshape(B * k, 3, 3)
        mk = m.repeat_interleave(k, 0)
        # kernel scale: the threshold, or less where the start's Sampson distances say the data are cleaner
        # (twice their median-based scale, 1.4826 median |r|), so that exact inliers refine to an exact model
        r0 = err.gather(1, order[..., None].expand(-1, -1, N)).reshape(B * k, N).sqrt()
        med = torch.where(mk, r0, float("nan")).nanmedian(-1).values
        sigma = (2.0 * 1.4826 * torch.nan_to_num(med, nan=thr)).clamp(thr * 1e-3, thr)
        models, _ = refine_essential(start, xi.repeat_interleave(k, 0), xj.repeat_interleave(k, 0), mk, sigma=sigma,
                                     iterations=refine_iterations)
        models = models.view(B, k, 3, 3)
        err = sampson_sq(models, xi, xj)
    model, inliers, _ = pick_best(models, err, thr_sq, m)
    num = inliers.sum(-1)
    return TwoViewResult(model, inliers, num, (num >= 5) & enough)


def find_homography_ransac(pts_i: torch.Tensor, pts_j: torch.Tensor, mask: torch.Tensor, threshold_px: float = 1.0,
                           iterations: int = 50, repeats: int = 1,
                           generators: list[torch.Generator] | None = None, preview: int = 256) -> TwoViewResult:
    """Homography ``x_j ~ H x_i`` by batched four-point DLT RANSAC (kornia ``find_homography_dlt``) with a
    weighted DLT refit on each repeat's winner's inliers.

    Runs :func:`dfvo.geometry.ransac.hypothesise_and_verify`; inliers are rows whose Torr geometric error
    (:func:`homography_error_sq`) is below ``threshold_px`` pixels. The result is the best of the winners and
    their refits (most inliers, then lowest truncated error).

    Args:
        pts_i, pts_j: (B,N,2) pixels. mask: (B,N) bool. threshold_px: pixels (official 1).
        iterations, repeats: samples per repeat and repeats.
        generators: one generator per frame (None: global RNG).
        preview: rows (random, per frame, with replacement) on which all candidates are ranked.

    Convention:
        ``H`` maps pixels of image i (previous) to pixels of image j (current), ``H[2, 2] = 1`` where finite.

    Returns:
        :class:`TwoViewResult` with ``model`` = H (B,3,3) float64; ``success`` False with fewer than 4 rows.
    """
    _check(pts_i, pts_j, mask, None, "find_homography_ransac")
    KORNIA_CHECK(threshold_px > 0, f"find_homography_ransac: threshold_px must be > 0, got {threshold_px}")
    B, N = mask.shape
    enough = mask.sum(-1) >= 4
    if N < 4 or not bool(enough.any()):
        return _fail(B, N, True, pts_i.device)
    m = mask & enough[:, None]
    xi = torch.where(m[..., None], pts_i.to(torch.float64), 0.0)
    xj = torch.where(m[..., None], pts_j.to(torch.float64), 0.0)
    thr_sq = float(threshold_px) ** 2

    def solve(rows: torch.Tensor) -> torch.Tensor:
        S = rows.shape[1]
        return find_homography_dlt(_gather_rows(xi, rows).view(B * S, 4, 2),
                                   _gather_rows(xj, rows).view(B * S, 4, 2)).view(B, S, 1, 3, 3)

    def residual(models: torch.Tensor, rows: torch.Tensor | None, exact: bool) -> torch.Tensor:
        return homography_error_sq(models, _gather_rows(xi, rows), _gather_rows(xj, rows))

    win = hypothesise_and_verify(m, 4, solve, residual, thr_sq, iterations, repeats, generators, preview)
    w = win.inliers.to(torch.float64).view(B * repeats, N)
    ref = find_homography_dlt(xi.repeat_interleave(repeats, 0), xj.repeat_interleave(repeats, 0), w)
    ok = (w.sum(-1) >= 4) & torch.isfinite(ref).all(-1).all(-1)
    ref = torch.where(ok[:, None, None], ref, win.models.view(B * repeats, 3, 3)).view(B, repeats, 3, 3)
    models = torch.cat([win.models, ref], 1)
    model, inliers, _ = pick_best(models, torch.cat([win.err_sq, homography_error_sq(ref, xi, xj)], 1), thr_sq, m)
    num = inliers.sum(-1)
    return TwoViewResult(model, inliers, num, (num >= 4) & enough)

def ray_depths(R: torch.Tensor, t: torch.Tensor, x_i: torch.Tensor,
               x_j: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Closed-form two-view depths of normalised rays under ``T_cur_prev = [R | t]``.

    Solves ``z_j x_j = z_i R x_i + t`` in the least-squares sense of the cross product with ``x_j``:
    ``z_i = -((x_j x t) . (x_j x R x_i)) / |x_j x R x_i|^2``; exact on exact data, and much cheaper than a
    per-point SVD.

    Convention:
        R (B,M,3,3), t (B,M,3): candidate motions ``T_cur_prev`` (frame-i points into camera j). x_i, x_j
        (B,N,2): normalised coordinates in images i (previous) and j (current). Returns z_i, z_j (B,M,N):
        depths in cameras i and j, in the unit of ``t``.
    """
    hi = torch.cat([x_i, torch.ones_like(x_i[..., :1])], -1)
    hj = torch.cat([x_j, torch.ones_like(x_j[..., :1])], -1)
    Rx = torch.einsum("bmrc,bnc->bmnr", R, hi)
    a = torch.linalg.cross(hj[:, None].expand_as(Rx), Rx, dim=-1)
    b = torch.linalg.cross(hj[:, None].expand_as(Rx), t[:, :, None].expand_as(Rx), dim=-1)
    z_i = -(a * b).sum(-1) / (a * a).sum(-1).clamp_min(1e-30)
    z_j = z_i * Rx[..., 2] + t[:, :, None, 2]
    return z_i, z_j


def decompose_essential(E: torch.Tensor, K: torch.Tensor, pts_i: torch.Tensor, pts_j: torch.Tensor,
                        mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Decompose E into ``T_cur_prev = [R | t]`` (unit t): of the four solutions of kornia's
    ``decompose_essential_matrix``, keep the one with most valid rows in front of both cameras (cheirality,
    as kornia's ``motion_from_essential_choose_solution`` does, with closed-form depths :func:`ray_depths`).

    Convention:
        E (B,3,3) with ``x_j^T E x_i = 0`` on normalised coordinates; K (B,3,3); pts_i, pts_j (B,N,2) pixels in
        images i (previous) and j (current); mask (B,N) bool. Returns R (B,3,3), t (B,3) float64 of
        ``T_cur_prev`` (frame-i points into camera j), and ``in_front`` (B,N) bool: valid rows passing
        cheirality. A non-finite E gives a pose with no row in front.
    """
    _check(pts_i, pts_j, mask, K, "decompose_essential")
    Kd = K.to(torch.float64)
    xi, xj = normalise_points(pts_i.to(torch.float64), Kd), normalise_points(pts_j.to(torch.float64), Kd)
    finite = torch.isfinite(E).all(-1).all(-1)
    safe = torch.where(finite[:, None, None], E.to(torch.float64), torch.eye(3, dtype=torch.float64, device=E.device))
    R1, R2, t = decompose_essential_matrix(safe)
    t = t.reshape(-1, 3)
    t = t / t.norm(dim=-1, keepdim=True).clamp_min(1e-30)
    Rs = torch.stack([R1, R1, R2, R2], 1)
    ts = torch.stack([t, -t, t, -t], 1)
    z_i, z_j = ray_depths(Rs, ts, xi, xj)
    front = mask[:, None] & (z_i > 0) & (z_j > 0) & finite[:, None, None]
    best = front.sum(-1).argmax(-1)
    ar = torch.arange(E.shape[0], device=E.device)
    return Rs[ar, best], ts[ar, best], front[ar, best]
