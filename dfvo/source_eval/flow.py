"""``python -m dfvo.evaluate task=flow``: optical flow on KITTI flow 2012/2015, the DF-VO paper's flow table.

For every training pair ``NNNNNN_10`` → ``NNNNNN_11`` of a KITTI layout (``gt_dir`` = the ``training`` folder, see
:class:`dfvo.data.flow_datasets.KittiFlow`) a flow source gives the forward flow (and the backward flow for the
BestN rows), which is scored against ``flow_noc`` / ``flow_occ`` (whichever exist) at the ground truth's size:

- sources: ``network`` (:class:`dfvo.sources.networks.NetworkFlow`, refined as ``infer.py`` refines it when
  ``refine.iterations`` > 0), ``dis`` (:class:`dfvo.sources.dis.DISFlow`), ``oracle`` (the ground truth itself:
  AEPE 0, a check of the plumbing), ``pred`` (KITTI-format flow PNGs ``pred_dir/NNNNNN_10.png``; backward flows
  ``NNNNNN_11.png`` = 11 → 10 on frame 11's pixels, optional; the images are not needed: ``pred`` and ``oracle`` read
  the ground truth's flows and their size alone). A ``working_size`` resizes the images before the source; its flow
  is resized back (vectors scaled).
- ``all`` rows: every pixel with ground truth. ``bestn`` rows (the paper's "+ BestN"): only the pixels that the
  forward-backward inconsistency (:func:`dfvo.matching.consistency.forward_backward_inconsistency`, computed on
  the flows at the ground truth's size) selects: the N most consistent (``best_n``), DF-VO's ``local_best_k``
  (:func:`dfvo.matching.selection.select_correspondences`) or those under ``max_inconsistency`` (``threshold``).
- metrics (:mod:`dfvo.eval.flow_metrics`): ``aepe`` = mean over pairs of each pair's mean EPE (the usual KITTI
  practice), ``aepe_pixels`` = mean EPE over all pixels of all pairs, ``out_N`` = % of pixels with EPE > N px (the
  paper's Out-1), ``fl_all`` = % with EPE > 3 px and > 5 % of the true magnitude (KITTI devkit), both pooled over
  the pixels of all pairs.

Settings: :class:`dfvo.source_eval.config.FlowEvalConfig` (the ``flow:`` node of the command).
"""

from __future__ import annotations

import time
from dataclasses import asdict
from enum import Enum
from pathlib import Path
from typing import Any

import torch

from dfvo.data.flow_datasets import KittiFlow, resize_flow
from dfvo.data.flow_io import read_kitti_flow
from dfvo.data.image_io import DatasetError, read_image
from dfvo.data.transforms import resize_image
from dfvo.eval.flow_metrics import flow_error_sums, kitti_fill_invalid, metrics_from_sums
from dfvo.matching.consistency import forward_backward_inconsistency
from dfvo.matching.flow_refinement import refine_forward_backward
from dfvo.matching.selection import select_correspondences
from dfvo.source_eval.config import FlowEvalConfig, FlowSelectionEvalConfig, task_settings
from dfvo.sources import find_checkpoint
from dfvo.sources.dis import DISFlow
from dfvo.sources.networks import NetworkFlow

__all__ = ["evaluate_flow_task", "flow_settings", "format_flow_table", "selection_mask"]

LAYOUTS = {"kitti2015": 2015, "kitti2012": 2012}


def flow_settings(cfg: Any) -> FlowEvalConfig:
    """The ``flow:`` node of ``cfg`` as a :class:`FlowEvalConfig` (missing keys: its defaults; unknown: an error)."""
    return task_settings(FlowEvalConfig, cfg, "flow")


def _build_source(s: FlowEvalConfig, kind: str) -> Any:
    if kind == "network":
        return NetworkFlow(find_checkpoint(s.checkpoint, "flow.checkpoint"), s.variant, device=str(s.device),
                           input_size=s.input_size)
    if kind == "dis":
        return DISFlow(str(s.preset), device=str(s.device))
    return None


def _read_pred(path: Path, hw: tuple[int, int], fill: bool, what: str) -> torch.Tensor:
    if not path.is_file():
        raise FileNotFoundError(f"pred_dir: {what} {path} does not exist (expected a KITTI flow PNG per pair, named "
                                "like the ground truth)")
    flow, valid = read_kitti_flow(path)
    if tuple(flow.shape[-2:]) != hw:
        raise ValueError(f"pred_dir: {path} is {flow.shape[1]}x{flow.shape[2]}, the ground truth is {hw[0]}x{hw[1]}")
    return kitti_fill_invalid(flow, valid)[0] if fill else flow


def selection_mask(flow_fwd: torch.Tensor, flow_bwd: torch.Tensor, sel: FlowSelectionEvalConfig) -> torch.Tensor:
    """(1,H,W) bool: the pixels of ``flow_fwd`` (2,H,W) that forward-backward consistency with ``flow_bwd`` (2,H,W)
    selects (``sel``: the ``selection`` settings)."""
    H, W = flow_fwd.shape[-2:]
    incon = forward_backward_inconsistency(flow_fwd[None].float(), flow_bwd[None].float())
    if sel.method == "threshold":
        return (incon[0] < float(sel.max_inconsistency)).cpu()
    c = select_correspondences(flow_fwd[None].float(), incon, method=str(sel.method), num=sel.num_for(H, W),
                               grid=tuple(sel.grid), max_inconsistency=float(sel.max_inconsistency),
                               min_valid_fraction=float(sel.min_valid_fraction),
                               min_region_fraction=float(sel.min_region_fraction), crop_top=float(sel.crop_top),
                               relaxed_inconsistency=())  # the selection as configured, no retry
    pts = c.pts_i[0][c.mask[0]].round().long().cpu()
    mask = torch.zeros(H * W, dtype=torch.bool)
    mask[pts[:, 1] * W + pts[:, 0]] = True
    return mask.view(1, H, W)


def _pair_flows(kind: str, src: Any, pair: Any, img1: torch.Tensor | None, img2: torch.Tensor | None, gt: dict,
                s: FlowEvalConfig, pred_dir: Path | None, size: tuple[int, int] | None, hw: tuple[int, int]
                ) -> tuple[torch.Tensor, torch.Tensor | None]:
    if kind == "oracle":
        return gt["occ" if "occ" in gt else "noc"][0], None
    if kind == "pred":
        fwd = _read_pred(pred_dir / f"{pair.name}_10.png", hw, bool(s.fill_invalid), "prediction")
        bwd_path = Path(s.pred_bwd_dir or pred_dir) / f"{pair.name}_11.png"
        bwd = _read_pred(bwd_path, hw, bool(s.fill_invalid), "backward prediction") if bwd_path.is_file() else None
        return fwd, bwd
    a, b = (img1, img2) if size is None else (resize_image(img1, *size), resize_image(img2, *size))
    fwd, bwd = src(a[None], b[None])
    if kind == "network" and s.refine.iterations > 0:  # as infer.py refines the network's flow, at the working size
        fwd, bwd = refine_forward_backward(a[None].to(fwd.device), b[None].to(fwd.device), fwd, bwd, s.refine)
    fwd, bwd = fwd[0].float().cpu(), bwd[0].float().cpu()
    if size is not None:
        ones = torch.ones(1, *fwd.shape[-2:], dtype=torch.bool)
        fwd, bwd = resize_flow(fwd, ones, hw)[0], resize_flow(bwd, ones, hw)[0]
    return fwd, bwd


def _aggregate(per_pair: list[dict], mask: str, subset: str, thresholds: list[float]) -> dict[str, Any] | None:
    sums = [p["_sums"][mask][subset] for p in per_pair if mask in p["_sums"] and subset in p["_sums"][mask]]
    if not sums:
        return None
    pooled = {k: sum(s[k] for s in sums) for k in sums[0]}
    m = metrics_from_sums(pooled)
    per = [s["epe_sum"] / s["num_pixels"] for s in sums if s["num_pixels"]]
    out: dict[str, Any] = {"aepe": sum(per) / len(per) if per else None, "aepe_pixels": m["aepe"]}
    out.update({f"out_{t:g}": m[f"out_{t:g}"] for t in thresholds})
    out.update({"fl_all": m["fl"], "num_pixels": m["num_pixels"], "num_pairs": len(per)})
    return out


def evaluate_flow_task(cfg: Any) -> dict[str, Any]:
    """Evaluate a flow source on a KITTI flow layout (``cfg.gt_dir``) or precomputed flows (``cfg.pred_dir``).

    Args:
        cfg: the command's config: ``gt_dir`` (KITTI ``training`` folder), optional ``pred_dir``, and the ``flow``
            node (:class:`FlowEvalConfig`; missing keys take its defaults).

    Returns:
        ``{"task", "layout", "gt_dir", "pred_dir", "source", "working_size", "selection", "num_pairs",
        "metrics": {"noc"|"occ": {"all": {...}, "bestn": {...} | None}}, "per_pair": [...],
        "source_seconds_per_pair"}``; each metric block holds ``aepe``, ``aepe_pixels``, ``out_N``, ``fl_all``
        (percent), ``num_pixels``, ``num_pairs``.
    """
    s = flow_settings(cfg)
    gt_dir = cfg.get("gt_dir")
    if not gt_dir:
        raise ValueError("task=flow needs gt_dir=PATH (a KITTI flow 'training' folder with image_2/ or colored_0/ "
                         "and flow_occ/ or flow_noc/)")
    pred_dir = Path(cfg["pred_dir"]) if cfg.get("pred_dir") else None
    kind = str(s.source)
    kind = ("pred" if pred_dir else "network") if kind == "auto" else kind
    if kind == "pred" and (pred_dir is None or not pred_dir.is_dir()):
        raise FileNotFoundError(f"flow.source=pred: pred_dir={pred_dir} is not a folder of KITTI flow PNGs")
    size = tuple(s.working_size) if s.working_size else None
    root = Path(gt_dir)
    train = root / "training" if (root / "training").is_dir() else root
    mask_kind = "occ" if (train / "flow_occ").is_dir() else "noc"
    need_images = kind not in ("pred", "oracle")  # precomputed flows are scored against the ground truth alone
    try:
        pairs = KittiFlow(root, version=LAYOUTS[str(s.layout)], mask=mask_kind, images=need_images).pairs
    except FileNotFoundError as err:
        raise type(err)(f"{err} (flow.layout={s.layout}; kitti2015 reads image_2/, kitti2012 colored_0/)") from err
    if s.frames:
        wanted = [str(f) for f in s.frames]
        missing = sorted(set(wanted) - {p.name for p in pairs})
        if missing:
            raise DatasetError(f"flow.frames: {missing} have no ground truth under {train}")
        pairs = [p for p in pairs if p.name in wanted]
    if s.max_pairs:
        pairs = pairs[: int(s.max_pairs)]
    src = _build_source(s, kind)
    thresholds = [float(t) for t in s.thresholds]
    per_pair, seconds = [], 0.0
    for pair in pairs:
        gt = {m: read_kitti_flow(pair.extra[m]) for m in ("noc", "occ") if m in pair.extra}
        img1 = img2 = None
        if need_images:
            img1 = read_image(pair.image1)
            img2 = read_image(pair.image2, expected_size=tuple(img1.shape[-2:]))
        first = img1 if img1 is not None else next(iter(gt.values()))[0]
        hw, what = tuple(first.shape[-2:]), pair.image1 if img1 is not None else pair.extra[next(iter(gt))]
        t0 = time.perf_counter()
        fwd, bwd = _pair_flows(kind, src, pair, img1, img2, gt, s, pred_dir, size, hw)
        seconds += time.perf_counter() - t0
        sel = selection_mask(fwd, bwd, s.selection) if bwd is not None else None
        sums: dict[str, dict] = {}
        for m, (gt_flow, valid) in gt.items():
            if tuple(gt_flow.shape[-2:]) != hw:
                raise DatasetError(f"{pair.extra[m]} is {gt_flow.shape[1]}x{gt_flow.shape[2]}, {what} is "
                                   f"{hw[0]}x{hw[1]}")
            sums[m] = {"all": flow_error_sums(fwd, gt_flow, valid, tuple(thresholds))}
            if sel is not None:
                sums[m]["bestn"] = flow_error_sums(fwd, gt_flow, valid & sel, tuple(thresholds))
        entry: dict[str, Any] = {"name": pair.name, "_sums": sums,
                                 "selected_pixels": int(sel.sum()) if sel is not None else None}
        for m in sums:
            entry[m] = {k: metrics_from_sums(v) for k, v in sums[m].items()}
        per_pair.append(entry)
    metrics = {m: {sub: _aggregate(per_pair, m, sub, thresholds) for sub in ("all", "bestn")}
               for m in ("noc", "occ") if any(m in p["_sums"] for p in per_pair)}
    for p in per_pair:
        p.pop("_sums")
    sel_cfg = {k: (v.value if isinstance(v, Enum) else v) for k, v in asdict(s.selection).items()}
    label = {"dis": f"dis ({s.preset})", "network": f"network (refined: {s.refine.mode}, {s.refine.iterations} "
             "iterations)" if s.refine.iterations > 0 else "network"}.get(kind, kind)
    return {"task": "flow", "layout": str(s.layout), "gt_dir": str(train),
            "pred_dir": str(pred_dir) if pred_dir else None, "source": label,
            "working_size": list(size) if size else None,
            "selection": sel_cfg, "num_pairs": len(per_pair), "metrics": metrics, "per_pair": per_pair,
            "source_seconds_per_pair": seconds / max(len(per_pair), 1)}


def format_flow_table(result: dict[str, Any]) -> str:
    """A text table of :func:`evaluate_flow_task`'s result: one row per mask (noc/occ) and subset (all/bestn)."""
    outs = [k for k in next((b for m in result["metrics"].values() for b in m.values() if b), {}) if
            k.startswith("out_")]
    head = f"{'mask':<5} {'subset':<7} {'AEPE px':>9} " + " ".join(f"{o.replace('_', '-').title():>7}" for o in outs)
    lines = [f"flow: {result['source']} on {result['layout']} ({result['num_pairs']} pairs), working size "
             f"{result['working_size'] or 'native'}", head + f" {'Fl-all':>7} {'count':>9}"]
    for m, rows in result["metrics"].items():
        for sub, b in rows.items():
            if b is None:
                lines.append(f"{m:<5} {sub:<7} {'(no backward flow)':>9}")
                continue
            fmt = lambda v: f"{v:7.2f}" if v is not None else f"{'-':>7}"  # noqa: E731
            aepe = f"{b['aepe']:9.3f}" if b["aepe"] is not None else f"{'-':>9}"
            lines.append(f"{m:<5} {sub:<7} {aepe} " + " ".join(fmt(b[o]) for o in outs)
                         + f" {fmt(b['fl_all'])} {b['num_pixels']:>9}")
    return "\n".join(lines)
