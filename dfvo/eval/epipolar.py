"""A flow's error where no true flow exists (real KITTI frames), measured against the true poses.

The true relative pose of frames i and j gives the fundamental matrix ``F = K^-T [t]x R K^-1``; a correct flow puts
every pixel x of frame i on its epipolar line in frame j, so the Sampson distance of ``(x, x + flow(x))`` to F
(:func:`dfvo.geometry.two_view.sampson_sq`) is a lower bound of the flow's error (it misses errors along the line).
``studies/kitti_flow_quality.py``, ``studies/flow_vs_classical.py`` and ``benchmarks/refine_schedules.py`` measure
flows this way.

Convention:
    ``T_prev_cur`` (4,4) maps points of the current camera into the previous one (``T_w_prev^-1 T_w_cur``); ``K``
    (3,3) in pixels of the images the flow is measured on; float64 numpy.
"""

from __future__ import annotations

import numpy as np

__all__ = ["fundamental_from_pose"]


def fundamental_from_pose(T_prev_cur: np.ndarray, K: np.ndarray) -> np.ndarray:
    """F (3,3) with ``x_cur^T F x_prev = 0`` for the relative pose ``T_cur_prev`` = inverse of ``T_prev_cur``."""
    T_cur_prev = np.linalg.inv(T_prev_cur)
    R, t = T_cur_prev[:3, :3], T_cur_prev[:3, 3]
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    Kinv = np.linalg.inv(K)
    return Kinv.T @ tx @ R @ Kinv
