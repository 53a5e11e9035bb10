"""Ground truth for your own frames and videos (``data.gt=FILE``): read in any trajectory format and laid on the
frames of the sequence.

Convention:
    A timestamped ground truth (TUM, EuRoC CSV) is associated with the frames by nearest timestamp within
    ``data.gt_tolerance`` seconds (frame times from the video container, or ``data.times=FILE``, one per line for
    every frame of the folder); a KITTI file with 13 numbers a line by its frame index; a KITTI file with 12 numbers
    line by line (one pose per frame of the folder). Frames without a ground-truth pose get NaN poses, which the
    metrics leave out (and count). The poses are ``T_w_c`` of the camera: a body-frame ground truth must be moved to
    the camera before (EuRoC's ``data=euroc`` does that with ``T_BS``).
"""

from __future__ import annotations

import logging
from dataclasses import replace
from typing import Any

import numpy as np

from dfvo.data.sequence import FrameSequence
from dfvo.io.association import match_timestamps
from dfvo.io.trajectory import read_times, read_trajectory

__all__ = ["attach_ground_truth"]

log = logging.getLogger("dfvo.data")


def attach_ground_truth(seq: FrameSequence, data: Any) -> FrameSequence:
    """``seq`` with ``poses`` (N,4,4) from ``data.gt`` (see the module docstring).

    Raises:
        ValueError: unreadable file, a timestamped ground truth without frame times, a 12-number file with fewer
            poses than frames, or no frame matched.
    """
    traj = read_trajectory(data.gt, data.gt_format)
    ids = seq.frame_ids if seq.frame_ids is not None else np.arange(seq.length)
    poses = np.full((seq.length, 4, 4), np.nan)
    if traj.timestamps is not None:
        stamps = seq.timestamps
        if getattr(data, "times", None):
            all_times = read_times(data.times)
            if len(all_times) <= int(np.max(ids)):
                raise ValueError(f"data.times={data.times}: {len(all_times)} timestamps for frames up to index "
                                 f"{int(np.max(ids))}; expected one line per frame of the folder")
            stamps = all_times[ids]
        if stamps is None:
            raise ValueError(f"data.gt={data.gt} is timestamped ({len(traj)} poses); give the frames' times with "
                             "data.times=FILE (seconds, one line per frame)")
        tol = float(getattr(data, "gt_tolerance", 0.02))
        i_frame, i_gt = match_timestamps(stamps, traj.timestamps, tol)
        poses[i_frame] = traj.poses[i_gt]
        how = f"by timestamp within {tol} s"
    elif traj.frame_ids is not None:
        where = {int(f): k for k, f in enumerate(traj.frame_ids)}
        for k, frame in enumerate(ids):
            if int(frame) in where:
                poses[k] = traj.poses[where[int(frame)]]
        how = "by frame index"
    else:
        if len(traj) <= int(np.max(ids)):
            raise ValueError(f"data.gt={data.gt}: {len(traj)} poses for frames up to index {int(np.max(ids))}; a "
                             "KITTI file of 12 numbers a line needs one pose per frame of the folder")
        poses = traj.poses[ids].astype(np.float64)
        how = "line by line"
    matched = int(np.isfinite(poses[:, 0, 0]).sum())
    if matched == 0:
        raise ValueError(f"data.gt={data.gt}: no frame of {seq.name} matched a ground-truth pose ({how})")
    log.info("data.gt=%s: %d of %d frames have a ground-truth pose (matched %s)", data.gt, matched, seq.length, how)
    return replace(seq, poses=poses)
