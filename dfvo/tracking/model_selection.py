"""Model selection between the E-tracker and the PnP-tracker: GRIC (E vs H), flow magnitude, and the
rotation-compensated parallax that keeps E whenever its translation is visible in the image."""

from __future__ import annotations

import torch
from kornia.core.check import KORNIA_CHECK_SHAPE

from dfvo.geometry.two_view import homography_error_sq, sampson_sq

__all__ = ["prefer_pnp_gric", "prefer_pnp_flow", "rotation_compensated_parallax", "homography_to_essential_residual"]


def prefer_pnp_gric(gric_e: torch.Tensor, gric_h: torch.Tensor) -> torch.Tensor:
    """(B,) bool: the homography explains the pair better (``GRIC_E > GRIC_H``: rotation-only, planar or
    standing-still pairs), so E is unreliable and PnP should be used."""
    return gric_e > gric_h


def prefer_pnp_flow(pts_i: torch.Tensor, pts_j: torch.Tensor, mask: torch.Tensor, threshold_px: float) -> torch.Tensor:
    """(B,) bool: the median flow magnitude of the selected rows is at most ``threshold_px`` pixels (too little
    parallax for E), the paper's cheap alternative to GRIC."""
    KORNIA_CHECK_SHAPE(pts_i, ["B", "N", "2"])
    mag = (pts_j - pts_i).norm(dim=-1)
    out = []
    for b in range(mag.shape[0]):
        vals = mag[b][mask[b]]
        out.append(bool(vals.numel() == 0 or float(vals.median()) <= threshold_px))
    return torch.tensor(out, dtype=torch.bool, device=pts_i.device)


def rotation_compensated_parallax(pts_i: torch.Tensor, pts_j: torch.Tensor, rows: torch.Tensor, R: torch.Tensor,
                                  K: torch.Tensor, level: float = 0.5) -> torch.Tensor:
    """(B,) float64: the quantile ``level`` over ``rows`` (B,N) of the distance (pixels) between ``pts_j`` (B,N,2) and
    ``pts_i`` (B,N,2) carried by the rotation ``R`` (B,3,3) of ``T_cur_prev`` alone (the infinite homography
    ``K R K^-1``, K (B,3,3)); NaN where a pair has no rows.

    This is the image motion the translation causes: zero for a pure rotation or a stop, whatever the rotation.
    GRIC compares how well E and H fit with a fixed noise level (0.8 px); when the flow is refined to a tenth of a
    pixel, a turning car's pair whose translation still moves the image by pixels is "explained" by H within that
    noise, and the pair would go to PnP (whose length is the depth network's, unfiltered). The paper's own argument
    for model selection is parallax; this measures it directly."""
    KORNIA_CHECK_SHAPE(pts_i, ["B", "N", "2"])
    Kd, Rd = K.to(torch.float64), R.to(torch.float64)
    Hinf = Kd @ Rd @ torch.linalg.inv(Kd)  # (B,3,3)
    x = torch.cat([pts_i.to(torch.float64), torch.ones_like(pts_i[..., :1], dtype=torch.float64)], -1)
    y = x @ Hinf.transpose(-1, -2)
    warped = y[..., :2] / y[..., 2:].clamp_min(1e-12)
    dist = (pts_j.to(torch.float64) - warped).norm(dim=-1)  # (B,N)
    out = torch.full((pts_i.shape[0],), float("nan"), dtype=torch.float64, device=pts_i.device)
    for b in range(pts_i.shape[0]):
        d = dist[b][rows[b]]
        if d.numel():
            out[b] = d.quantile(level)
    return out


def homography_to_essential_residual(H: torch.Tensor, E: torch.Tensor, K: torch.Tensor, pts_i: torch.Tensor,
                                     pts_j: torch.Tensor, rows: torch.Tensor, floor_px: float) -> torch.Tensor:
    """(B,) float64: the median geometric residual (pixels) of ``rows`` (B,N) under the homography ``H`` (B,3,3; pixels,
    ``x_j ~ H x_i``) over their median Sampson residual under the essential matrix ``E`` (B,3,3; normalised
    coordinates, K (B,3,3)), the latter at least ``floor_px`` (the flow's own noise: on exact data both residuals
    vanish); NaN where a pair has no rows. Near 1 or below when one plane carries the points (a planar scene: H fits
    them as well as E); several times 1 when their depths vary."""
    Kinv = torch.linalg.inv(K.to(torch.float64))
    F = Kinv.transpose(-1, -2) @ E.to(torch.float64) @ Kinv
    pi, pj = pts_i.to(torch.float64), pts_j.to(torch.float64)
    e_res = sampson_sq(F[:, None], pi, pj)[:, 0].sqrt()
    h_res = homography_error_sq(H.to(torch.float64)[:, None], pi, pj)[:, 0].sqrt()
    out = torch.full((pi.shape[0],), float("nan"), dtype=torch.float64, device=pi.device)
    for b in range(pi.shape[0]):
        if bool(rows[b].any()):
            out[b] = h_res[b][rows[b]].median() / e_res[b][rows[b]].median().clamp_min(floor_px)
    return out
