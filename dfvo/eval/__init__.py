"""Evaluation toolkit: trajectory I/O, alignment, KITTI odometry / flow / depth metrics, plots, reports.

Names are imported lazily (PEP 562) so that ``python -m dfvo.evaluate`` loads neither torch nor matplotlib
unless flow/depth metrics or plots are used.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "dfvo.eval.alignment": ("ALIGN_MODES", "AlignMode", "Association", "align_trajectory", "apply_alignment",
                            "associate_trajectories", "estimate_alignment", "match_timestamps", "rebase_to_first",
                            "umeyama"),
    "dfvo.eval.depth_metrics": ("compute_depth_metrics", "depth_errors"),
    "dfvo.eval.flow_metrics": ("compute_flow_metrics",),
    "dfvo.data.flow_io": ("read_kitti_flow", "read_png16", "write_kitti_flow", "write_png16"),  # moved there
    "dfvo.eval.odometry_metrics": ("SEGMENT_LENGTHS", "absolute_trajectory_error", "aligned_prediction",
                                   "evaluate_trajectory",
                                   "kitti_segment_errors", "relative_pose_error", "rotation_angle",
                                   "trajectory_distances"),
    "dfvo.eval.plots": ("frames_figure", "plot_frames", "plot_segment_errors", "plot_trajectory",
                        "segment_errors_figure", "trajectory_figure"),
    "dfvo.eval.report": ("evaluate_sequences", "find_sequences", "format_table", "sequence_name"),
    "dfvo.eval.trajectory_io": ("Trajectory", "TrajectoryWriter", "detect_format", "read_euroc", "read_kitti",
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
