"""``viewer=rerun``: every tracked frame into a Rerun recording ``OUT/run.rrd`` (:class:`dfvo.viewer.RerunRecorder`).

Convention:
    Frame ``k`` is logged at timeline index ``k`` with its pose ``T_w_c``, its image and (when computed) its depth,
    the flow and forward-backward inconsistency of the pair ``k-1 → k`` (on frame ``k-1``'s pixels), the pair's
    selected correspondences coloured by the tracker's inliers, the inliers triangulated with the pair's metric
    motion (in world coordinates), and the frame's row of ``frames.csv`` as scalars. Frame 0 is logged with the
    first pair.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from dfvo.geometry.camera import backproject_points
from dfvo.inference.config import ViewerConfig
from dfvo.inference.loop import FrameRecord
from dfvo.matching.consistency import forward_backward_inconsistency
from dfvo.tracking.diagnostics import FrameDiagnostics, TrackerUsed
from dfvo.tracking.scale import has_depth, triangulated_depths
from dfvo.viewer.rerun_recorder import RerunRecorder

__all__ = ["RerunObserver", "triangulated_inliers"]


def triangulated_inliers(record: FrameRecord, K: torch.Tensor, T_w_prev: np.ndarray) -> np.ndarray | None:
    """(M,3) world points of the record's inlier correspondences triangulated with its metric ``T_cur_prev``
    (None when the frame has no essential-matrix inliers)."""
    matches = record.result.matches
    if matches is None or matches.inliers is None or not bool(matches.inliers.any()):
        return None
    rows = matches.inliers
    T_cur_prev = torch.linalg.inv(record.result.T_prev_cur.to(torch.float64))
    Kd = K.to(torch.float64).reshape(1, 3, 3)
    pi = matches.pts_prev[rows].to(torch.float64)[None]
    pj = matches.pts_cur[rows].to(torch.float64)[None]
    z, _, front = triangulated_depths(T_cur_prev[None, :3, :3], T_cur_prev[None, :3, 3], Kd, pi, pj)
    keep = front[0] & (z[0] < 200.0)
    if not bool(keep.any()):
        return None
    X = backproject_points(pi[:, keep], z[:, keep], Kd)[0].numpy()
    return X @ T_w_prev[:3, :3].T + T_w_prev[:3, 3]


class RerunObserver:
    """Logs each :class:`FrameRecord` into ``path`` (see the module docstring).

    Args:
        path: the ``.rrd`` file. K: (3,3) working-size intrinsics. image_hw: working size.
        gt_poses: (N,4,4) ground truth to draw (as given), or None. spawn: also open the live viewer.
    """

    def __init__(self, path: Path, K: torch.Tensor, image_hw: tuple[int, int], gt_poses: np.ndarray | None = None,
                 spawn: bool = ViewerConfig.spawn) -> None:
        self.K = K.detach().cpu()
        self.recorder = RerunRecorder(path, self.K, image_hw, spawn=spawn, gt_poses=gt_poses)
        self.T_w_prev = np.eye(4)

    def on_frame(self, record: FrameRecord) -> None:
        """Log frame ``record.index`` (and frame 0 with the first record)."""
        if record.index == 1:
            depth0 = record.depth_prev.cpu() if has_depth(record.depth_prev) else None  # none: depth.every
            self.recorder.log_frame(0, np.eye(4), image=record.image_prev.cpu(), depth=depth0,
                                    diagnostics=_row(FrameDiagnostics(frame=0, tracker=TrackerUsed.init), {}))
        T_w = record.result.T_w_cur.detach().cpu().double().numpy()
        matches = record.result.matches
        incon = forward_backward_inconsistency(record.flow_fwd[None].cpu(), record.flow_bwd[None].cpu())[0]
        self.recorder.log_frame(
            record.index, T_w, image=record.image.cpu(), flow_fwd=record.flow_fwd.cpu(), inconsistency=incon,
            depth=record.depth.cpu() if has_depth(record.depth) else None,
            pts_prev=None if matches is None else matches.pts_prev.cpu(),
            pts_cur=None if matches is None else matches.pts_cur.cpu(),
            inlier=None if matches is None or matches.inliers is None else matches.inliers.cpu(),
            points_world=triangulated_inliers(record, self.K, self.T_w_prev),
            diagnostics=_row(record.result.diagnostics, record.stage_seconds))
        self.T_w_prev = T_w

    def close(self) -> None:
        self.recorder.close()


def _row(diagnostics: FrameDiagnostics, stage_seconds: dict[str, float]) -> dict[str, Any]:
    row = {k: v for k, v in diagnostics.as_row().items() if not k.startswith("time_")}
    return {**row, **stage_seconds}
