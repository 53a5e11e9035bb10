"""Where a trajectory's frame-to-frame error comes from: the translation lengths (the scale), or the directions and
rotations (the flow and the geometry).

DF-VO takes each relative pose's rotation and translation direction from the flow (epipolar geometry) and only the
translation length from the depth network. :func:`scale_free` replaces every predicted relative translation's length by
the true one, which removes the scale error and leaves what the flow and the geometry did; the ratio of predicted to
true lengths is the scale error itself. ``studies/error_decomposition.py`` and ``studies/flow_vs_classical.py`` report
it.

Convention:
    Poses ``T_w_k`` ``(N,4,4)`` float64 of the same N frames (already paired, e.g. by
    :func:`dfvo.io.association.associate_trajectories`); relative motions ``T_k_k+1 = T_w_k^-1 T_w_k+1``.
"""

from __future__ import annotations

import numpy as np

__all__ = ["relative", "compose", "scale_free"]


def relative(poses: np.ndarray) -> np.ndarray:
    """(N,4,4) ``T_w_k`` -> (N-1,4,4) ``T_k_k+1``."""
    return np.linalg.inv(poses[:-1]) @ poses[1:]


def compose(rel: np.ndarray) -> np.ndarray:
    """(N-1,4,4) ``T_k_k+1`` -> (N,4,4) ``T_w_k`` with ``T_w_0`` = identity (the inverse of :func:`relative` up to the
    first pose)."""
    out = [np.eye(4)]
    for T in rel:
        out.append(out[-1] @ T)
    return np.stack(out)


def scale_free(gt: np.ndarray, pred: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Split a prediction's relative motion into what the flow did and what the scale did.

    Args:
        gt, pred: (N,4,4) ``T_w_k`` of the same frames.

    Returns:
        ``(true_lengths, moving, direction_deg, length_ratio)``: the prediction with every relative translation
        rescaled to the true length (N,4,4); which of the N-1 pairs moved (true translation > 1 mm); per moving pair
        the angle between predicted and true translation (degrees) and predicted / true length.
    """
    rg, rp = relative(gt), relative(pred)
    lg, lp = np.linalg.norm(rg[:, :3, 3], axis=1), np.linalg.norm(rp[:, :3, 3], axis=1)
    moving = lg > 1e-3
    fixed = rp.copy()
    fixed[moving, :3, 3] *= (lg[moving] / np.maximum(lp[moving], 1e-12))[:, None]
    cos = np.einsum("ij,ij->i", rg[moving, :3, 3], rp[moving, :3, 3]) / np.maximum(lg[moving] * lp[moving], 1e-12)
    return compose(fixed), moving, np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))), lp[moving] / lg[moving]
