"""Sliding-window bundle adjustment of the latest step (``tracker.window``; opt-in, beyond the paper).

DF-VO decides each frame's motion from one pair and never revisits it. Here the last ``frames`` frames form a window:

- **Tracks.** The correspondences the tracker used for a pair start tracks, one per ``cell_px`` cell that no carried
  track holds; each following pair's forward flow carries a live track on (bilinear flow at its position) while the
  forward-backward inconsistency there stays below ``max_inconsistency`` and it stays in the image. (With
  ``flow.refine.mode=pyramid`` the dense flow away from the refined candidates is the network's own.)
- **Unknowns.** The window's poses ``T_0j`` (frame 0 of the window is fixed: the gauge) and each track's depth in
  the first window frame that sees it (its anchor ``a``), as an inverse depth ``rho``.
- **Cost** (Levenberg–Marquardt, Schur complement on the inverse depths)::

      sum_obs  w cauchy(|pi(T_0j^-1 T_0a X_i(rho_i)) - u_ij|)          reprojection into every later view
    + sum_i   ((log z_i - log(c zcnn_i)) / depth_log_std)^2          the depth network's shape of the scene
    + sum_k   xi_k^T C_k^-1 xi_k                                     the tracker's steps and their covariances

  ``w = 1 / (pixel_sigma^2 * tracker.covariance.inflation)``: the same correlated-noise factor the steps' own
  covariances carry (:mod:`dfvo.tracking.covariance`), so one pair's correspondences do not count twice as
  much as its step. ``c`` is the window's median ratio of triangulated to CNN depth, so the depth prior shapes the
  structure but does not set its scale: the scale is the steps' lengths' (the scale filter's). ``xi_k`` is the
  error of step ``k`` against the tracker's in the convention of :mod:`dfvo.geometry.pose_covariance`.

Only the latest step leaves the window: earlier poses were emitted already, so the result stays causal and
``VisualOdometry.step`` equals ``run``. The tracker's own state (motion model, scale filter, gates) keeps the
tracker's step: the window is a layer on top of the paper's tracker, one switch away. A constant-motion frame
empties the window (its flow is not trusted to carry tracks). A refinement that moves the step's rotation by more
than ``max_rotation_change_deg`` or its length by more than ``max_length_change`` (relative) is not used (flagged).

Frames and units: poses float64 (4,4) map a window frame's points into window frame 0; pixels (N,2) in the working
image; depths in metres (the unit of the steps' translations).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from dfvo.geometry.essential_refine import skew, so3_exp
from dfvo.geometry.pose_covariance import so3_log, step_error, symmetric
from dfvo.geometry.se3 import se3_inverse
from dfvo.geometry.two_view import normalised_rays, ray_depths
from dfvo.matching.flow_warp import inside_image, sample_at_pixels
from dfvo.tracking.config import WindowConfig
from dfvo.tracking.scale import sample_depth

__all__ = ["WindowRefiner", "WindowResult", "WindowProblem", "solve_window", "judge_refinement"]


@dataclass
class WindowResult:
    """The window's verdict on the latest step: ``T_prev_cur`` (4,4) float64 refined (None: not refined),
    ``num_tracks`` in the problem, ``length_ratio`` refined over tracked length, ``rotation_change_deg`` between
    the refined and the tracked rotation, ``rejected`` why a refinement was not used (None: used or not run)."""

    T_prev_cur: torch.Tensor | None = None
    num_tracks: int = 0
    length_ratio: float | None = None
    rotation_change_deg: float | None = None
    rejected: str | None = None


@dataclass
class WindowProblem:
    """One window's bundle adjustment problem.

    Attributes:
        steps: (n-1,4,4) float64 the tracker's ``T_prev_cur`` of the window's pairs (frame k-1 -> k), the priors.
        step_whitening: (n-1,6,6) float64 ``L`` with ``L^T L`` the inverse covariance of each step's error.
        obs: (M,n,2) float64 pixels of each track in each window frame (NaN: not seen there); every track is seen in
            at least two frames, contiguously.
        zcnn: (M,) float64 the depth network's depth of each track in its anchor frame (NaN: none).
        K: (3,3) float64 intrinsics.
    """

    steps: torch.Tensor
    step_whitening: torch.Tensor
    obs: torch.Tensor
    zcnn: torch.Tensor
    K: torch.Tensor


def _compose(T: torch.Tensor, xi: torch.Tensor) -> torch.Tensor:
    """``T exp(xi)`` to first order in the translation: (...,4,4) poses, (...,6) ``[omega, v]`` (right
    perturbation; the retraction of the Jacobians below)."""
    out = T.clone()
    out[..., :3, :3] = T[..., :3, :3] @ so3_exp(xi[..., :3])
    out[..., :3, 3] = T[..., :3, 3] + (T[..., :3, :3] @ xi[..., 3:, None])[..., 0]
    return out


def _step_errors(poses: torch.Tensor, steps: torch.Tensor) -> torch.Tensor:
    """(...,n-1,6) errors ``[phi, dt]`` of the window's steps ``T_0,k-1^-1 T_0,k`` of (...,n,4,4) poses against
    the tracker's (n-1,4,4), in :mod:`dfvo.geometry.pose_covariance`'s convention (the truth there is the
    tracker's step here: the prior)."""
    return step_error(se3_inverse(poses[..., :-1, :, :]) @ poses[..., 1:, :, :], steps)


class _Geometry:
    """Per-observation quantities of a problem at fixed track assignment (anchors, rays, observation list)."""

    def __init__(self, prob: WindowProblem) -> None:
        obs = prob.obs
        M, n, _ = obs.shape
        seen = torch.isfinite(obs).all(-1)  # (M,n)
        self.anchor = seen.to(torch.int8).argmax(1)  # first seen frame (contiguous tracks)
        self.ray = normalised_rays(obs[torch.arange(M), self.anchor][None], prob.K[None])[0]  # (M,3), z = 1
        later = seen & (torch.arange(n)[None] > self.anchor[:, None])
        self.track, self.view = later.nonzero(as_tuple=True)  # (O,) each observation after the anchor
        self.uv = obs[self.track, self.view]
        self.src = self.anchor[self.track].long()
        self.last = torch.where(seen, torch.arange(n)[None].expand(M, n), -1).max(1).values
        self.M = M


def _project(geo: _Geometry, poses: torch.Tensor, rho: torch.Tensor, K: torch.Tensor
             ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Each observation's point: residual (O,2) px, in front of the viewing camera (O,) bool, anchor -> view
    rotation (O,3,3), the point in the anchor frame ``Xa`` and in the viewing frame ``Xv`` (O,3 each)."""
    T_pair = se3_inverse(poses)[:, None] @ poses[None]  # (n,n,4,4): frame j's points into frame i
    T_rel = T_pair[geo.view, geo.src]
    R = T_rel[:, :3, :3]
    Xa = geo.ray[geo.track] / rho[geo.track, None]
    Xv = (R @ Xa[..., None])[..., 0] + T_rel[:, :3, 3]
    front = Xv[:, 2] > 1e-6
    Zs = torch.where(front, Xv[:, 2], torch.ones_like(Xv[:, 2]))
    proj = torch.stack([K[0, 0] * Xv[:, 0] / Zs + K[0, 2], K[1, 1] * Xv[:, 1] / Zs + K[1, 2]], -1)
    return proj - geo.uv, front, R, Xa, Xv


def _reprojection(geo: _Geometry, poses: torch.Tensor, rho: torch.Tensor, K: torch.Tensor
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Residuals (O,2) px, their Jacobians on the viewing pose (O,2,6), on the anchor pose (O,2,6) and on the
    inverse depth (O,2), and (O,) bool "in front of the viewing camera" (right perturbations ``T exp(xi)``,
    ``xi = [omega, v]``: see :func:`_compose`)."""
    r, front, R, Xa, Xv = _project(geo, poses, rho, K)
    Zs = torch.where(front, Xv[:, 2], torch.ones_like(Xv[:, 2]))
    fx, fy = K[0, 0], K[1, 1]
    zero = torch.zeros_like(Zs)
    dpi = torch.stack([torch.stack([fx / Zs, zero, -fx * Xv[:, 0] / Zs ** 2], -1),
                       torch.stack([zero, fy / Zs, -fy * Xv[:, 1] / Zs ** 2], -1)], 1)  # (O,2,3)
    J_view = torch.cat([dpi @ skew(Xv), -dpi], -1)
    dpiR = dpi @ R
    J_anchor = torch.cat([-(dpiR @ skew(Xa)), dpiR], -1)
    J_rho = -(dpiR @ Xa[..., None])[..., 0] / rho[geo.track, None]
    return r, J_view, J_anchor, J_rho, front


def _cauchy_weight(norm: torch.Tensor, c: float) -> torch.Tensor:
    """IRLS weights of the Cauchy loss (a redescending influence: a track on a moving object barely counts)."""
    return 1.0 / (1.0 + (norm / c) ** 2)


def _cauchy_cost(norm: torch.Tensor, c: float) -> torch.Tensor:
    """The Cauchy loss of residual norms (pixels) with scale ``c``."""
    return 0.5 * c ** 2 * torch.log1p((norm / c) ** 2)


def _initial_depths(geo: _Geometry, poses: torch.Tensor, prob: WindowProblem, min_parallax_deg: float
                    ) -> tuple[torch.Tensor, torch.Tensor]:
    """(M,) initial depths in the anchor frames and the factor ``c`` (triangulated over CNN depth; NaN when fewer
    than 10 tracks have both): each track triangulated between its anchor and its last view; where that is poorly
    conditioned, ``c`` times its CNN depth (or the median triangulated depth without one)."""
    idx = torch.arange(geo.M)
    T_rel = se3_inverse(poses[geo.last]) @ poses[geo.anchor]
    ray_l = normalised_rays(prob.obs[idx, geo.last][None], prob.K[None])[0]
    x_last = ray_l[:, :2]
    z_a, z_l = ray_depths(T_rel[:, None, :3, :3], T_rel[:, None, :3, 3], geo.ray[:, None, :2], x_last[:, None])
    z_a, z_l = z_a[:, 0, 0], z_l[:, 0, 0]
    Rray = (T_rel[:, :3, :3] @ geo.ray[..., None])[..., 0]
    cos = (Rray * ray_l).sum(-1) / (Rray.norm(dim=-1) * ray_l.norm(dim=-1))
    parallax = torch.rad2deg(torch.arccos(cos.clamp(-1.0, 1.0)))
    good = (z_a > 0) & (z_l > 0) & (parallax >= min_parallax_deg) & torch.isfinite(z_a)
    has_cnn = torch.isfinite(prob.zcnn) & (prob.zcnn > 0)
    both = good & has_cnn
    c = float((z_a[both] / prob.zcnn[both]).median()) if int(both.sum()) >= 10 else float("nan")
    fallback = float(z_a[good].median()) if int(good.sum()) > 0 else 10.0
    z = torch.where(has_cnn & (c == c), c * prob.zcnn, torch.full_like(z_a, fallback))
    z = torch.where(good & ~has_cnn, z_a, z)
    return z.clamp_min(1e-3), torch.tensor(c, dtype=torch.float64)


def solve_window(prob: WindowProblem, cfg: WindowConfig, inflation: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Bundle-adjust one window: returns the poses (n,4,4) float64 (``T_0j``, frame 0 the identity) and the
    inverse depths (M,) of the tracks in their anchor frames. Starts from the tracker's steps chained."""
    n = prob.obs.shape[1]
    poses = [torch.eye(4, dtype=torch.float64)]
    for S in prob.steps:
        poses.append(poses[-1] @ S)
    poses = torch.stack(poses)
    geo = _Geometry(prob)
    z0, c = _initial_depths(geo, poses, prob, cfg.min_parallax_deg)
    rho = 1.0 / z0
    w_px = 1.0 / (cfg.pixel_sigma ** 2 * inflation)
    # the depth prior shapes the structure at the steps' scale: without a measured ratio c it would set the scale
    has_cnn = torch.isfinite(prob.zcnn) & (prob.zcnn > 0) & torch.isfinite(c)
    log_prior = torch.where(has_cnn, torch.log(c * prob.zcnn.clamp_min(1e-9)), torch.zeros_like(prob.zcnn))
    w_depth = has_cnn.to(torch.float64) / cfg.depth_log_std ** 2
    L = prob.step_whitening
    P = 6 * (n - 1)

    def cost(poses: torch.Tensor, rho: torch.Tensor) -> float:
        r, front, *_ = _project(geo, poses, rho, prob.K)
        # an observation behind its camera costs as much as a 1000-px residual: no step gains by moving it there
        norm = torch.where(front, r.norm(dim=-1), torch.full_like(r[:, 0], 1e3))
        rep = _cauchy_cost(norm, cfg.robust_px).sum() * w_px
        dep = (w_depth * (-torch.log(rho) - log_prior) ** 2).sum() * 0.5
        e = (L @ _step_errors(poses, prob.steps)[..., None])[..., 0]
        return float(rep + dep + 0.5 * (e ** 2).sum())

    lam = 1e-3
    current = cost(poses, rho)
    for _ in range(int(cfg.iterations)):
        r, J_view, J_anchor, J_rho, front = _reprojection(geo, poses, rho, prob.K)
        w = _cauchy_weight(r.norm(dim=-1), cfg.robust_px) * front * w_px  # (O,)
        O = len(w)
        Jp = torch.zeros(O, 2, n, 6, dtype=torch.float64)
        Jp[torch.arange(O), :, geo.view] = J_view
        Jp[torch.arange(O), :, geo.src] += J_anchor
        Jp = Jp[:, :, 1:].reshape(O, 2, P)  # frame 0 is fixed
        Jw = Jp * w[:, None, None]
        Hpp = Jp.reshape(2 * O, P).T @ Jw.reshape(2 * O, P)
        gp = -(Jw.reshape(2 * O, P).T @ r.reshape(2 * O))
        Hpl = torch.zeros(geo.M, P, dtype=torch.float64).index_add_(
            0, geo.track, (Jw * J_rho[..., None]).sum(1)).T
        Hll = torch.zeros(geo.M, dtype=torch.float64).index_add_(0, geo.track, w * (J_rho ** 2).sum(-1))
        gl = torch.zeros(geo.M, dtype=torch.float64).index_add_(0, geo.track, -w * (J_rho * r).sum(-1))
        # depth prior: d(-log rho)/d rho = -1/rho
        e_d = -torch.log(rho) - log_prior
        Hll = Hll + w_depth / rho ** 2
        gl = gl - w_depth * e_d * (-1.0 / rho)
        # step priors: numeric Jacobian of the whitened errors on the free poses (central differences)
        h = 1e-6
        free = torch.cat([torch.eye(P, dtype=torch.float64), -torch.eye(P, dtype=torch.float64)]) * h
        delta = torch.cat([torch.zeros(2 * P, 1, 6, dtype=torch.float64), free.reshape(2 * P, n - 1, 6)], 1)
        pert = _compose(poses.expand(2 * P, n, 4, 4), delta)
        e_pert = (L @ _step_errors(pert, prob.steps)[..., None])[..., 0].reshape(2 * P, -1)
        Js = ((e_pert[:P] - e_pert[P:]) / (2 * h)).T  # (6(n-1), P)
        e0 = (L @ _step_errors(poses, prob.steps)[..., None])[..., 0].reshape(-1)
        Hpp = Hpp + Js.T @ Js
        gp = gp - Js.T @ e0
        while True:
            Hpp_d = Hpp + lam * torch.diag(Hpp.diagonal().clamp_min(1e-12))
            Hll_d = Hll * (1.0 + lam) + 1e-12
            Hpl_s = Hpl / Hll_d
            S = Hpp_d - Hpl_s @ Hpl.T
            rhs = gp - Hpl_s @ gl
            dp = torch.linalg.solve(symmetric(S), rhs)
            dl = (gl - Hpl.T @ dp) / Hll_d
            step = torch.zeros(n, 6, dtype=torch.float64)
            step[1:] = dp.reshape(n - 1, 6)
            new_poses, new_rho = _compose(poses, step), (rho + dl).clamp_min(1e-6)
            new = cost(new_poses, new_rho)
            if new < current:
                poses, rho, current, lam = new_poses, new_rho, new, max(lam / 10.0, 1e-9)
                break
            lam *= 10.0
            if lam > 1e6:
                return poses, rho
    return poses, rho


def judge_refinement(T_prev_cur: torch.Tensor, refined: torch.Tensor, num_tracks: int, cfg: WindowConfig
                     ) -> WindowResult:
    """The window's verdict on a refined step (4,4) against the tracker's (4,4), both float64 ``T_prev_cur``: used
    unless it turns the step by more than ``cfg.max_rotation_change_deg`` or changes its length by more than
    ``cfg.max_length_change`` (relative; a step of zero length must stay at zero)."""
    tracked_len, refined_len = float(T_prev_cur[:3, 3].norm()), float(refined[:3, 3].norm())
    ratio = refined_len / tracked_len if tracked_len > 1e-9 else (1.0 if refined_len <= 1e-9 else math.inf)
    turn = math.degrees(float(so3_log(refined[:3, :3] @ T_prev_cur[:3, :3].T).norm()))
    if turn > cfg.max_rotation_change_deg or abs(ratio - 1.0) > cfg.max_length_change:
        return WindowResult(None, num_tracks, ratio, turn, (
            f"window: refinement not used (rotation change {turn:.3f} deg, length ratio {ratio:.3f}; limits "
            f"tracker.window.max_rotation_change_deg={cfg.max_rotation_change_deg}, max_length_change="
            f"{cfg.max_length_change})"))
    return WindowResult(refined, num_tracks, ratio, turn)


class WindowRefiner:
    """The window's state between frames (tracks, the tracker's steps) and the refinement of each latest step.

    Args:
        cfg: ``tracker.window``. inflation: ``tracker.covariance.inflation`` (see the module docstring).
        max_depth, depth_crop_top: the depth network's depths are read as the scale stage reads them
            (``tracker.scale.max_depth``, ``tracker.scale.depth_crop_top``): none beyond ``max_depth`` metres or in
            the top ``depth_crop_top`` of the image.
    """

    def __init__(self, cfg: WindowConfig, inflation: float, max_depth: float, depth_crop_top: float) -> None:
        self.cfg, self.inflation = cfg, float(inflation)
        self.max_depth, self.depth_crop_top = float(max_depth), float(depth_crop_top)
        self.reset()

    def reset(self) -> None:
        """An empty window (the next pair starts it)."""
        W = int(self.cfg.frames)
        self.obs = torch.full((0, W, 2), float("nan"), dtype=torch.float64)
        self.zcnn = torch.full((0, W), float("nan"), dtype=torch.float64)
        self.alive = torch.zeros(0, dtype=torch.bool)
        self.steps: list[torch.Tensor] = []
        self.whitening: list[torch.Tensor] = []

    def update(self, T_prev_cur: torch.Tensor, covariance: torch.Tensor | None, tracked: bool,
               pts_prev: torch.Tensor, pts_cur: torch.Tensor, flow: torch.Tensor, inconsistency: torch.Tensor,
               depth_prev: torch.Tensor, K: torch.Tensor) -> WindowResult:
        """Add pair (k-1, k) and refine its step (the window's state lives on the CPU, in float64).

        Args:
            T_prev_cur: (4,4) the tracker's step; covariance: (6,6) its error covariance; tracked: the step is E's
                or PnP's (False, or no covariance: constant motion, the window empties).
            pts_prev, pts_cur: (N,2) pixels of the correspondences the tracker used (start new tracks).
            flow: (1,2,H,W) forward flow k-1 -> k; inconsistency: (1,1,H,W) its forward-backward inconsistency
                (carry the live tracks). depth_prev: (1,1,H,W) metres of frame k-1 (NaN or <= 0: none).
            K: (3,3) intrinsics.
        """
        if not tracked or covariance is None:
            self.reset()
            return WindowResult()
        cfg, W = self.cfg, int(self.cfg.frames)
        T_prev_cur = T_prev_cur.detach().to("cpu", torch.float64)
        flow, inconsistency, depth_prev = (x.detach().cpu() for x in (flow, inconsistency, depth_prev))
        H, Wd = flow.shape[-2:]
        # the depth of frame k-1 (the newest column) where tracks see it
        last = self.obs[:, -1]
        self.zcnn[:, -1] = self._depth_at(depth_prev, last)  # NaN so far: a column is filled when its frame is k-1
        # carry the live tracks into frame k
        moved = torch.full_like(last, float("nan"))
        live = self.alive.nonzero(as_tuple=True)[0]  # seen in frame k-1
        if len(live):
            q = last[live] + sample_at_pixels(flow, last[live]).T
            carried = (sample_at_pixels(inconsistency, last[live])[0] < cfg.max_inconsistency) & inside_image(q, H, Wd)
            moved[live[carried]] = q[carried]
            self.alive = torch.zeros_like(self.alive)
            self.alive[live[carried]] = True
        self.obs = torch.cat([self.obs[:, 1:], moved[:, None]], 1)
        self.zcnn = torch.cat([self.zcnn[:, 1:], torch.full_like(self.zcnn[:, :1], float("nan"))], 1)
        self._start_tracks(pts_prev.detach().to("cpu", torch.float64), pts_cur.detach().to("cpu", torch.float64),
                           moved[self.alive], depth_prev, H, Wd)
        keep = torch.isfinite(self.obs).all(-1).sum(1) >= 2
        self.obs, self.zcnn, self.alive = self.obs[keep], self.zcnn[keep], self.alive[keep]
        self.steps = (self.steps + [T_prev_cur])[-(W - 1):]
        self.whitening = (self.whitening + [_whitening(covariance.detach().cpu())])[-(W - 1):]
        n = len(self.steps) + 1
        if n < 3:
            return WindowResult()
        obs = self.obs[:, -n:]
        seen = torch.isfinite(obs).all(-1)
        latest = int(seen[:, -1].sum())  # tracks through the step being refined
        if latest < cfg.min_tracks:
            return WindowResult(num_tracks=latest, rejected=f"window: {latest} tracks reach this frame "
                                                            f"(< tracker.window.min_tracks={cfg.min_tracks})")
        anchor = seen.to(torch.int8).argmax(1)
        zcnn = self.zcnn[:, -n:][torch.arange(len(obs)), anchor]
        prob = WindowProblem(torch.stack(self.steps), torch.stack(self.whitening), obs, zcnn,
                             K.detach().to("cpu", torch.float64))
        try:
            poses, _ = solve_window(prob, cfg, self.inflation)
        except RuntimeError as exc:  # a singular system (degenerate tracks): the tracker's step stands
            return WindowResult(num_tracks=latest, rejected=f"window: the bundle adjustment failed ({exc})"[:200])
        refined = se3_inverse(poses[-2]) @ poses[-1]
        if not bool(torch.isfinite(refined).all()):
            return WindowResult(num_tracks=latest, rejected="window: the bundle adjustment diverged (non-finite)")
        return judge_refinement(T_prev_cur, refined, latest, cfg)

    def _start_tracks(self, pts_prev: torch.Tensor, pts_cur: torch.Tensor, carried: torch.Tensor,
                      depth_prev: torch.Tensor, H: int, W: int) -> None:
        """New tracks from the pair's (N,2) correspondences (frame k-1, frame k): the first of each ``cell_px`` cell
        of frame k that holds no carried track (``carried`` (C,2) pixels in frame k); points outside are skipped."""
        inside = inside_image(pts_cur, H, W) & inside_image(pts_prev, H, W)
        pp, pc = pts_prev[inside], pts_cur[inside]
        if not len(pp):
            return
        cell_px, cols = int(self.cfg.cell_px), math.ceil(W / self.cfg.cell_px)
        cells = math.ceil(H / cell_px) * cols
        cell = _cells(pc, cell_px, cols)
        taken = torch.zeros(cells, dtype=torch.bool)
        taken[_cells(carried, cell_px, cols)] = True
        rows = torch.arange(len(pc))
        first = torch.full((cells,), len(pc), dtype=torch.long).scatter_reduce_(0, cell, rows, "amin")
        fresh = ~taken[cell] & (first[cell] == rows)
        pp, pc = pp[fresh], pc[fresh]
        W_ = int(self.cfg.frames)
        new_obs = torch.full((len(pp), W_, 2), float("nan"), dtype=torch.float64)
        new_obs[:, -2], new_obs[:, -1] = pp, pc
        new_z = torch.full((len(pp), W_), float("nan"), dtype=torch.float64)
        new_z[:, -2] = self._depth_at(depth_prev, pp)
        self.obs = torch.cat([self.obs, new_obs])
        self.zcnn = torch.cat([self.zcnn, new_z])
        self.alive = torch.cat([self.alive, torch.ones(len(pp), dtype=torch.bool)])

    def _depth_at(self, depth: torch.Tensor, pts: torch.Tensor) -> torch.Tensor:
        """(N,) float64 the depth map (1,1,H,W) at (N,2) pixels as the scale stage reads it (nearest pixel), NaN
        where unusable (outside, in the cropped top, beyond ``max_depth``, no depth)."""
        if not len(pts):
            return torch.zeros(0, dtype=torch.float64)
        z, ok = sample_depth(depth, torch.nan_to_num(pts, nan=-1.0)[None], self.max_depth, self.depth_crop_top)
        return torch.where(ok[0], z[0], torch.full_like(z[0], float("nan")))


def _cells(pts: torch.Tensor, cell_px: int, cols: int) -> torch.Tensor:
    """(N,) long cell index of (N,2) pixels (inside the image) on a grid of ``cell_px`` cells ``cols`` wide."""
    q = (pts / cell_px).floor().long()
    return q[:, 1] * cols + q[:, 0]


def _whitening(covariance: torch.Tensor) -> torch.Tensor:
    """(6,6) ``L`` with ``L^T L = C^-1`` of a (6,6) covariance (eigenvalues floored: a near-singular covariance
    gives a very stiff but finite prior)."""
    s, V = torch.linalg.eigh(symmetric(covariance.to(torch.float64)))
    return (V / s.clamp_min(1e-18).sqrt()).T
