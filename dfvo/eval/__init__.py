"""Evaluation toolkit: alignment, KITTI odometry / flow / depth metrics, plots, reports.

The trajectory files (:mod:`dfvo.io.trajectory`) and the pairing of two trajectories (:mod:`dfvo.io.association`)
live in :mod:`dfvo.io`, below the dataset readers that use them too; their names are offered here as well, so that
one ``from dfvo.eval import ...`` gives the whole toolkit. Names are imported lazily (PEP 562), so that
``from dfvo.eval import read_trajectory`` loads neither torch nor matplotlib.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "dfvo.eval.alignment": ("ALIGN_MODES", "AlignMode", "align_trajectory", "apply_alignment", "estimate_alignment",
                            "rebase_to_first", "umeyama"),
    "dfvo.eval.depth_metrics": ("compute_depth_metrics", "depth_errors"),
    "dfvo.eval.flow_metrics": ("compute_flow_metrics",),
    "dfvo.eval.ground_truth_checks": ("constant_rate_segments", "pair_rotations_deg", "pairs_in_segments",
                                      "rotation_changes_deg"),
    "dfvo.eval.odometry_metrics": ("SEGMENT_LENGTHS", "absolute_trajectory_error", "aligned_prediction",
                                   "evaluate_trajectory",
                                   "kitti_segment_errors", "relative_pose_error", "relative_pose_errors",
                                   "rotation_angle",
                                   "trajectory_distances"),
    "dfvo.eval.plots": ("frames_figure", "plot_frames", "plot_segment_errors", "plot_trajectory",
                        "segment_errors_figure", "trajectory_figure"),
    "dfvo.eval.report": ("evaluate_sequences", "find_sequences", "format_table", "sequence_name"),
    "dfvo.io.association": ("Association", "associate_trajectories", "match_timestamps"),
    "dfvo.io.trajectory": ("Trajectory", "TrajectoryWriter", "detect_format", "read_euroc", "read_kitti",
                                "read_kitti_poses", "read_times", "read_trajectory", "read_tum", "read_tum_poses",
                                "write_euroc_poses", "write_kitti_poses", "write_trajectory", "write_tum_poses"),
}
_WHERE = {name: module for module, names in _EXPORTS.items() for name in names}
__all__ = sorted(_WHERE)


def __getattr__(name: str) -> Any:
    if name not in _WHERE:
        raise AttributeError(f"module 'dfvo.eval' has no attribute {name!r}")
    return getattr(importlib.import_module(_WHERE[name]), name)


def __dir__() -> list[str]:
    return __all__
