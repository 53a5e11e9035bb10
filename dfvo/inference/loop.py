"""The inference loop: frames → flow and depth sources → :class:`dfvo.tracking.VisualOdometry`, one record per frame.

Convention:
    Flow and depth are computed for ``batch_size`` consecutive frame pairs at once (one network batch), and the
    tracker takes the same pairs as one batch (``VisualOdometry.run``). Network flow is refined photometrically
    (``refine``) before the forward-backward test; oracle and classical flows are used as they are. The depth given
    to the tracker is that of the earlier frame of each pair, in metres (with ``tracker.scale.depth_views=2`` also
    the later frame's); each frame's depth is computed once. Frame 0's pose is the identity and has no record.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import torch

from dfvo.inference.frames import FrameSequence
from dfvo.inference.timing import StageTimer
from dfvo.matching.flow_refinement import FlowRefinementConfig, refine_forward_backward
from dfvo.sources.base import DepthSource, FlowSource
from dfvo.tracking import FrameResult, VisualOdometry
from dfvo.tracking.config import TrackerMode

__all__ = ["FrameRecord", "track_sequence"]


@dataclass
class FrameRecord:
    """Everything known about one tracked frame ``index`` (the pair ``index-1 → index``).

    Attributes:
        image_prev, image: (3,H,W) frames ``index-1`` and ``index``. flow_fwd, flow_bwd: (2,H,W) the flows the
        tracker used. depth_prev: (1,H,W) metres. depth: (1,H,W) of frame ``index`` when it was computed (two-view
        scale), else None. result: the tracker's pose and diagnostics.
        stage_seconds: this frame's share of each stage (``t_flow``, ``t_refine``, ``t_depth``, ``t_tracker``).
    """

    index: int
    image_prev: torch.Tensor
    image: torch.Tensor
    flow_fwd: torch.Tensor
    flow_bwd: torch.Tensor
    depth_prev: torch.Tensor
    result: FrameResult
    stage_seconds: dict[str, float]
    depth: torch.Tensor | None = None


def track_sequence(seq: FrameSequence, flow_src: FlowSource, depth_src: DepthSource, vo: VisualOdometry, *,
                   refine: FlowRefinementConfig | None, batch_size: int, timer: StageTimer, device: str = "cpu",
                   finetuner: object | None = None) -> Iterator[FrameRecord]:
    """Track ``seq`` and yield one :class:`FrameRecord` per frame 1..N-1, in order, as soon as it is known.

    Args:
        seq: the frames. flow_src, depth_src: the sources. vo: the odometry (its state continues across calls).
        refine: photometric refinement of the flow (None: none). batch_size: frame pairs per batch.
        timer: receives ``load``, ``finetune``, ``flow``, ``refine``, ``depth``, ``tracker`` seconds.
        finetuner: optional online flow finetuner (:class:`dfvo.training.online_flow.OnlineFlowFinetuner`).
    """
    K = seq.K.to(device)[None]
    two_views = vo.cfg.scale.depth_views == 2 and vo.cfg.mode != TrackerMode.pnp
    depth_carry: torch.Tensor | None = None  # depth of the first frame of the next batch (= this batch's last)
    batch = max(1, int(batch_size))
    with timer("load"):
        prev_img = seq.image(0)[None].to(device)
    for first in range(0, seq.length - 1, batch):
        idx = list(range(first, min(first + batch, seq.length - 1)))
        n = len(idx)
        with timer("load"):
            imgs = torch.cat([prev_img] + [seq.image(i + 1)[None].to(device) for i in idx])
        prev_img = imgs[-1:]
        if finetuner is not None and finetuner.active:
            with timer("finetune"):
                for k in range(n):
                    finetuner.step(*flow_src.network_inputs(imgs[k:k + 1], imgs[k + 1:k + 2]))
        with timer("flow"):
            flow_fwd, flow_bwd = flow_src(imgs[:-1], imgs[1:], idx)
        t_refine = 0.0
        if refine is not None:
            with timer("refine"):
                flow_fwd, flow_bwd = refine_forward_backward(imgs[:-1], imgs[1:], flow_fwd, flow_bwd, refine)
            t_refine = timer.last["refine"]
        with timer("depth"):
            depth_next = None
            if two_views:
                later = depth_src(imgs[1:], [i + 1 for i in idx])
                first_depth = depth_src(imgs[:1], idx[:1]) if depth_carry is None else depth_carry
                depth = torch.cat([first_depth, later[:-1]])
                depth_next, depth_carry = later, later[-1:]
            else:
                depth = depth_src(imgs[:-1], idx)
        with timer("tracker"):
            results = vo.run(flow_fwd, flow_bwd, depth, K.expand(n, 3, 3), batch_size=n, depths_next=depth_next)
        share = {"t_flow": timer.last["flow"] / n, "t_refine": t_refine / n, "t_depth": timer.last["depth"] / n,
                 "t_tracker": timer.last["tracker"] / n}
        for k, (i, res) in enumerate(zip(idx, results, strict=True)):
            yield FrameRecord(i + 1, imgs[k], imgs[k + 1], flow_fwd[k], flow_bwd[k], depth[k], res, share,
                              None if depth_next is None else depth_next[k])
