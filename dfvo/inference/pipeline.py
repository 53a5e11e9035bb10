"""The inference loop: frames → flow and depth sources → :class:`dfvo.tracking.VisualOdometry` → files.

Convention:
    Network flow is refined photometrically (``flow.refine``, :mod:`dfvo.matching.flow_refinement`) before the
    forward-backward test; the oracle's true flow is used as it is. Flow and depth are computed for ``batch_size``
    consecutive frame pairs at once (one network batch), and the tracker takes the same pairs as one batch
    (``VisualOdometry.run``: selection and E-RANSAC batched, the rest in order). Frame 0's pose is the identity;
    frame k's pose ``T_w_k`` is written to ``OUT/SEQ.txt`` (KITTI format) as soon as it is known, with its row of
    ``frames.csv``.
    Depth given to the tracker is the depth of the earlier frame of each pair, in metres (with
    ``scale.scale_depth_views=2`` also the later frame's; each frame's depth is computed once).
"""

from __future__ import annotations

import logging
import os
import sys
import time
from dataclasses import asdict, fields
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from dfvo.inference.frames import FrameSequence, build_sequence
from dfvo.inference.outputs import FramesCsv, PoseWriter, fallback_summary, write_json
from dfvo.matching.flow_refinement import FlowRefinementConfig, refine_forward_backward
from dfvo.sources import build_depth_source, build_flow_source, check_sources

__all__ = ["run_inference", "tracker_config", "flow_refinement_config", "TRACKER_GROUPS"]

log = logging.getLogger("dfvo.infer")

TRACKER_GROUPS = ("tracker", "correspondence", "scale", "model_selection")


def tracker_config(cfg: DictConfig) -> Any:
    """Build a :class:`dfvo.tracking.TrackerConfig` from the groups ``tracker``, ``correspondence``, ``scale``,
    ``model_selection`` (keys named ``name`` are labels; every other key must be a TrackerConfig field)."""
    from dfvo.tracking import TrackerConfig

    valid = {f.name for f in fields(TrackerConfig)}
    kwargs: dict[str, Any] = {}
    for group in TRACKER_GROUPS:
        values = OmegaConf.to_container(cfg[group], resolve=True) if cfg.get(group) is not None else {}
        for key, value in values.items():
            if key == "name":
                continue
            if key not in valid:
                raise ValueError(f"conf/{group}: unknown tracker setting {key!r}; TrackerConfig fields are "
                                 f"{sorted(valid)}")
            kwargs[key] = tuple(value) if isinstance(value, list) else value
    return TrackerConfig(**kwargs)


def _diag_row(frame: int, diag: dict[str, Any]) -> dict[str, Any]:
    row = dict(diag)
    row["frame"] = frame
    tracker = str(diag.get("tracker", ""))
    reason = str(diag.get("fallback_reason") or "")
    row["constant_motion"] = int("const" in tracker.lower())
    pnp_ok = diag.get("pnp_success")
    reason = reason.lower()
    row["pnp_failed"] = int(pnp_ok is False or (pnp_ok is None and "pnp" in reason and "fail" in reason))
    return row


class _Timer:
    def __init__(self) -> None:
        self.total: dict[str, float] = {}

    def add(self, key: str, seconds: float) -> None:
        self.total[key] = self.total.get(key, 0.0) + seconds


def _tensorboard(cfg: DictConfig, out: Path) -> Any:
    if not cfg.get("tensorboard", {}).get("enabled", False):
        return None
    from torch.utils.tensorboard import SummaryWriter

    return SummaryWriter(str(out / "tensorboard"))


def prepare_out_dir(out_dir: Any) -> Path:
    """Create the output folder ``out_dir`` (parents included) and check that it is writable.

    Raises:
        ValueError: ``out_dir`` is not set.
        OSError: the folder cannot be created or written (a path component is a file, no permission, ...); the
            message names ``out_dir`` and the cause.
    """
    if out_dir is None or not str(out_dir).strip():
        raise ValueError("out_dir is not set; pass out_dir=FOLDER (created if missing)")
    out = Path(str(out_dir))
    blocker = next((p for p in (out, *out.parents) if p.exists() and not p.is_dir()), None)
    if blocker is not None:
        raise NotADirectoryError(f"out_dir={out}: cannot create the output folder, {blocker} is a file, not a "
                                 "folder; pass out_dir= a folder path")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise type(err)(f"out_dir={out}: cannot create the output folder ({err.strerror or err}); pass out_dir= a "
                        "writable folder path") from err
    if not os.access(out, os.W_OK | os.X_OK):
        raise PermissionError(f"out_dir={out}: the output folder is not writable; pass out_dir= a writable folder")
    return out


def run_inference(cfg: DictConfig) -> dict[str, Any]:
    """Run DF-VO on one sequence and write its outputs (see :mod:`dfvo.inference.outputs`).

    Args:
        cfg: the composed ``conf/infer.yaml`` (groups ``data``, ``img_res``, ``flow``, ``depth``, the tracker
            groups; ``seq``, ``out_dir``, ``batch_size``, ``online_finetune``, ``tensorboard``, ``align``).

    Returns:
        Summary dict (also written to ``OUT/summary.json``): sequence, frames, fps, timing, fallback, metrics.
    """
    out = prepare_out_dir(cfg.get("out_dir"))  # before the (slow) sources: a bad out_dir fails at once
    if cfg.get("num_threads"):
        torch.set_num_threads(int(cfg.num_threads))
    device = str(cfg.get("device", "cpu"))
    seq = build_sequence(cfg.data, cfg.get("seq"), cfg.img_res)
    if seq.length < 2:
        raise ValueError(f"sequence {seq.name} has {seq.length} frame(s); expected at least 2")
    check_sources(cfg.flow, cfg.depth, seq.world)  # every missing checkpoint in one error, before loading any
    flow_src = build_flow_source(cfg.flow, seq.world, device)
    refine = flow_refinement_config(cfg.flow) if flow_src.name == "network" else None
    depth_src = build_depth_source(cfg.depth, seq.world, device)
    from dfvo.tracking import VisualOdometry

    vo = VisualOdometry(tracker_config(cfg))
    sources = {"flow": flow_src.name, "depth": depth_src.name,
               "flow_checkpoint": str(getattr(flow_src, "checkpoint", "")) or None,
               "depth_checkpoint": str(getattr(depth_src, "checkpoint", "")) or None,
               "flow_refinement": asdict(refine) if refine is not None else None}
    finetuner = None
    if cfg.get("online_finetune", False):
        if not hasattr(flow_src, "model"):
            raise ValueError("online_finetune=true needs flow=network (the oracle flow cannot be finetuned)")
        from dfvo.training.online_flow import OnlineFlowConfig, OnlineFlowFinetuner

        ocfg = OnlineFlowConfig(**OmegaConf.to_container(cfg.get("online", {}) or {}, resolve=True))
        finetuner = OnlineFlowFinetuner(flow_src.model, ocfg)
    writer = _tensorboard(cfg, out)
    try:
        summary = _loop(cfg, seq, flow_src, refine, depth_src, vo, finetuner, out, writer, device)
    finally:
        if writer is not None:
            writer.close()
    summary["sources"] = sources
    summary["online_finetune"] = finetuner is not None
    write_json(out / "summary.json", summary)
    return summary


def flow_refinement_config(flow_cfg: Any) -> FlowRefinementConfig | None:
    """``flow.refine`` as a :class:`FlowRefinementConfig`; None when absent or ``iterations`` is 0."""
    values = flow_cfg.get("refine") if flow_cfg is not None else None
    if not values:
        return None
    values = OmegaConf.to_container(values, resolve=True)
    valid = {f.name for f in fields(FlowRefinementConfig)}
    unknown = sorted(set(values) - valid)
    if unknown:
        raise ValueError(f"flow.refine: unknown setting(s) {unknown}; expected {sorted(valid)}")
    refine = FlowRefinementConfig(**values)
    return refine if refine.iterations > 0 else None


def _loop(cfg: DictConfig, seq: FrameSequence, flow_src: Any, refine: FlowRefinementConfig | None, depth_src: Any,
          vo: Any, finetuner: Any, out: Path, writer: Any, device: str) -> dict[str, Any]:
    from tqdm import tqdm

    poses = PoseWriter(out / f"{seq.name}.txt")
    table = FramesCsv(out / "frames.csv")
    K = seq.K.to(device)[None]
    T_w = np.eye(4)
    poses.write(T_w)
    table.write({"frame": 0, "tracker": "init"})
    traj, rows, timer = [T_w.copy()], [], _Timer()
    two_view_scale = vo.cfg.scale_depth_views == 2  # the tracker also needs the later frame's depth of each pair
    depth_carry: torch.Tensor | None = None  # depth of the first frame of the next batch (= this batch's last)
    batch = max(1, int(cfg.get("batch_size", 4)))
    n_pairs = seq.length - 1
    bar = tqdm(total=n_pairs, desc=f"dfvo {seq.name}", unit="frame", disable=not cfg.get("progress", True))
    start_wall = time.perf_counter()
    t0 = time.perf_counter()
    prev_img = seq.image(0)[None].to(device)
    timer.add("load", time.perf_counter() - t0)
    try:
        for first in range(0, n_pairs, batch):
            idx = list(range(first, min(first + batch, n_pairs)))
            t0 = time.perf_counter()
            imgs = torch.cat([prev_img] + [seq.image(i + 1)[None].to(device) for i in idx])
            timer.add("load", time.perf_counter() - t0)
            prev_img = imgs[-1:]
            t0 = time.perf_counter()
            if finetuner is not None and finetuner.active:
                for k in range(len(idx)):
                    finetuner.step(*flow_src.network_inputs(imgs[k:k + 1], imgs[k + 1:k + 2]))
                timer.add("finetune", time.perf_counter() - t0)
                t0 = time.perf_counter()
            flow_fwd, flow_bwd = flow_src(imgs[:-1], imgs[1:], idx)
            t_flow = time.perf_counter() - t0
            t_refine = 0.0
            if refine is not None:
                t0 = time.perf_counter()
                flow_fwd, flow_bwd = refine_forward_backward(imgs[:-1], imgs[1:], flow_fwd, flow_bwd, refine)
                t_refine = time.perf_counter() - t0
                timer.add("refine", t_refine)
            t0 = time.perf_counter()
            depth_next = None
            if two_view_scale:
                later = depth_src(imgs[1:], [i + 1 for i in idx])
                depth = torch.cat([depth_src(imgs[:1], idx[:1]) if depth_carry is None else depth_carry, later[:-1]])
                depth_next, depth_carry = later, later[-1:]
            else:
                depth = depth_src(imgs[:-1], idx)
            t_depth = time.perf_counter() - t0
            timer.add("flow", t_flow)
            timer.add("depth", t_depth)
            t0 = time.perf_counter()
            results = vo.run(flow_fwd, flow_bwd, depth, K.expand(len(idx), 3, 3), batch_size=len(idx),
                             depths_next=depth_next)
            t_track = (time.perf_counter() - t0) / len(idx)
            for k, (i, res) in enumerate(zip(idx, results)):
                timer.add("tracker", t_track)
                diag = dict(res.diagnostics)
                for key, v in diag.items():
                    if key.startswith("time_") and isinstance(v, float | int):
                        timer.add(key[5:], float(v))
                T_w = res.T_w_cur.detach().cpu().double().numpy()
                poses.write(T_w)
                traj.append(T_w.copy())
                row = _diag_row(i + 1, diag)
                row.update(t_flow=t_flow / len(idx), t_refine=t_refine / len(idx), t_depth=t_depth / len(idx),
                           t_tracker=t_track)
                table.write(row)
                rows.append(row)
                if writer is not None and (i % int(cfg.tensorboard.get("every", 10)) == 0):
                    from dfvo.inference.tb_logging import log_frame

                    log_frame(writer, i + 1, imgs[k], flow_fwd[k], flow_bwd[k], depth[k], row, cfg)
            bar.update(len(idx))
            bar.set_postfix(fps=f"{(first + len(idx)) / (time.perf_counter() - start_wall):.2f}")
    except KeyboardInterrupt:
        log.warning("interrupted: %s holds the first %d poses", poses.path, poses.count)
        raise
    finally:
        bar.close()
        poses.close()
        table.close()
    wall = time.perf_counter() - start_wall
    return _finish(cfg, seq, np.stack(traj), rows, timer, wall, out, writer)


NOT_ABLATION_KEYS = ("out_dir", "data.root", "progress", "num_threads", "hydra.", "hydra/")
SEQUENCE_KEYS = ("seq", "data.seq")  # the table's columns, not its rows


def _choices() -> dict[str, str]:
    """The config-group choices of this Hydra job (empty outside Hydra), for the ablation table."""
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return {}
    return {k: str(v) for k, v in HydraConfig.get().runtime.choices.items() if not k.startswith("hydra")}


def _overrides() -> dict[str, str]:
    """The command line's ``key=value`` overrides that are not group choices (e.g. ``flow.refine.iterations=0``),
    without paths and run settings; empty outside Hydra. The ablation table shows the ones that vary."""
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return {}
    groups = set(_choices())
    out = {}
    for item in HydraConfig.get().overrides.task:
        key, sep, value = item.lstrip("+~").partition("=")
        if (sep and key not in groups and "@" not in key and key not in SEQUENCE_KEYS
                and not key.startswith(NOT_ABLATION_KEYS)):
            out[key] = value
    return out


def _finish(cfg: DictConfig, seq: FrameSequence, pred: np.ndarray, rows: list[dict[str, Any]], timer: _Timer,
            wall: float, out: Path, writer: Any) -> dict[str, Any]:
    n_pairs = len(rows)
    summary: dict[str, Any] = {
        "sequence": seq.name, "frames": seq.length, "pose_file": str(out / f"{seq.name}.txt"),
        "fps": n_pairs / wall if wall > 0 else None, "wall_s": wall,
        "timing_ms_per_frame": {k: 1000 * v / max(n_pairs, 1) for k, v in timer.total.items()},
        "fallback": fallback_summary(rows, float(cfg.get("warn_fallback_rate", 0.2))),
        "choices": _choices(),
        "overrides": _overrides(),
    }
    from dfvo.eval import align_trajectory, evaluate_trajectory, plot_trajectory, rebase_to_first

    metrics = None
    gt_plotted, plotted, title = None, pred, seq.name
    if seq.poses is not None:
        metrics = {"sequence": seq.name, **evaluate_trajectory(seq.poses, pred, align=str(cfg.align))}
        write_json(out / "metrics.json", metrics)
        # plot the trajectories as they are evaluated: relative to their first frame, prediction aligned
        gt_plotted = rebase_to_first(seq.poses)
        plotted, _ = align_trajectory(gt_plotted, rebase_to_first(pred), str(cfg.align))
        title = f"{seq.name} (prediction aligned: {cfg.align})"
    plot_trajectory(gt_plotted, plotted, out / "trajectory.png", title=title)
    summary["metrics"] = metrics
    write_json(out / "summary.json", summary)
    if writer is not None:
        from dfvo.inference.tb_logging import log_trajectory

        log_trajectory(writer, seq.poses, pred, metrics)
    fb = summary["fallback"]
    log.info("%s: %d frames, %.2f FPS, timing ms/frame %s", seq.name, seq.length, summary["fps"] or 0.0,
             {k: round(v, 1) for k, v in summary["timing_ms_per_frame"].items()})
    if metrics is not None:
        log.info("metrics: %s", {k: v for k, v in metrics.items() if not isinstance(v, dict | list)})
    if fb["warn"]:
        msg = (f"\n{'!' * 78}\nWARNING: {fb['constant_motion']}/{fb['frames']} frames "
               f"({100 * fb['constant_motion_rate']:.0f}%) fell back to constant motion and PnP failed on "
               f"{fb['pnp_failed']} ({100 * fb['pnp_failed_rate']:.0f}%).\nThe trajectory is unreliable: check the "
               f"flow/depth sources, the image resolution and the intrinsics (see {out / 'frames.csv'}).\n"
               f"{'!' * 78}")
        log.warning("%d/%d frames fell back to constant motion, PnP failed on %d", fb["constant_motion"],
                    fb["frames"], fb["pnp_failed"])
        print(msg, file=sys.stderr, flush=True)
    return summary
