"""Multi-sequence evaluation of KITTI-format folders, the averaged summary, a text table and JSON output.

Convention:
    ``gt_dir/<seq>.txt`` and ``pred_dir/<seq>.txt`` are KITTI pose files. The ``average`` entry is the plain
    mean over sequences (not weighted by length) of each metric that has a value; sequences listed in
    ``exclude`` stay in the per-sequence output but not in the average.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dfvo.eval.odometry_metrics import evaluate_trajectory
from dfvo.eval.trajectory_io import read_kitti_poses

SUMMARY_KEYS = ("t_err_pct", "r_err_deg_per_100m", "ate_m", "rpe_m", "rpe_deg")


def evaluate_sequences(gt_dir: str | Path, pred_dir: str | Path, seqs: list[str] | None = None, align: str = "7dof",
                       exclude: list[str] | None = None, plot_dir: str | Path | None = None) -> dict:
    """Evaluate ``pred_dir/<seq>.txt`` against ``gt_dir/<seq>.txt`` for each sequence.

    Args:
        gt_dir: folder of ground-truth KITTI pose files.
        pred_dir: folder of predicted KITTI pose files.
        seqs: sequence names such as ``["09", "10"]``; None = every ``*.txt`` in ``pred_dir`` that has GT.
        align: ``6dof`` | ``7dof`` | ``scale`` | ``none``.
        exclude: sequences left out of the average (e.g. ``["01"]`` as in the DF-VO paper).
        plot_dir: when set, writes ``<seq>_trajectory.png`` and ``<seq>_segment_errors.png`` there.

    Returns:
        ``{"align", "sequences": {seq: evaluate_trajectory dict}, "average": {...,"sequences": [...]}}``.
    """
    gt_dir, pred_dir = Path(gt_dir), Path(pred_dir)
    for name, d in (("gt_dir", gt_dir), ("pred_dir", pred_dir)):
        if not d.is_dir():
            raise FileNotFoundError(f"{name}={d} is not a directory")
    if seqs is None:
        seqs = sorted(p.stem for p in pred_dir.glob("*.txt") if (gt_dir / p.name).is_file())
        if not seqs:
            raise FileNotFoundError(f"no <seq>.txt in pred_dir={pred_dir} has a matching file in gt_dir={gt_dir}")
    results = {}
    for seq in seqs:
        gt, pred = read_kitti_poses(gt_dir / f"{seq}.txt"), read_kitti_poses(pred_dir / f"{seq}.txt")
        if len(gt) != len(pred):
            raise ValueError(f"sequence {seq}: {gt_dir / f'{seq}.txt'} has {len(gt)} poses but "
                             f"{pred_dir / f'{seq}.txt'} has {len(pred)}")
        res = evaluate_trajectory(gt, pred, align=align)
        results[seq] = res
        if plot_dir is not None:
            from dfvo.eval.alignment import align_trajectory, rebase_to_first
            from dfvo.eval.plots import plot_segment_errors, plot_trajectory

            gt0, pred0 = rebase_to_first(gt), rebase_to_first(pred)
            plot_trajectory(gt0, align_trajectory(gt0, pred0, align)[0], Path(plot_dir) / f"{seq}_trajectory.png",
                            title=f"{seq} (align={align})")
            plot_segment_errors(res["per_length"], Path(plot_dir) / f"{seq}_segment_errors.png", title=seq)
    excluded = {str(e) for e in (exclude or [])}
    used = [s for s in seqs if s not in excluded]
    average: dict = {"sequences": used}
    for key in SUMMARY_KEYS:
        vals = [results[s][key] for s in used if results[s][key] is not None]
        average[key] = float(np.mean(vals)) if vals else None
    return {"align": align, "sequences": results, "average": average}


def format_table(result: dict) -> str:
    """A fixed-width text table of ``evaluate_sequences`` output (one row per sequence plus the average)."""
    head = f"{'seq':>8} {'frames':>7} {'t_err%':>8} {'r_err°/100m':>12} {'ATE m':>9} {'RPE m':>8} {'RPE °':>8}"
    lines = [f"alignment: {result['align']}", head, "-" * len(head)]

    def fmt(v, w, p):
        return f"{v:>{w}.{p}f}" if v is not None else f"{'-':>{w}}"

    for seq, r in result["sequences"].items():
        lines.append(f"{seq:>8} {r['num_frames']:>7d} {fmt(r['t_err_pct'], 8, 3)} "
                     f"{fmt(r['r_err_deg_per_100m'], 12, 3)} "
                     f"{fmt(r['ate_m'], 9, 3)} {fmt(r['rpe_m'], 8, 4)} {fmt(r['rpe_deg'], 8, 4)}")
    a = result["average"]
    lines.append("-" * len(head))
    lines.append(f"{'average':>8} {'':>7} {fmt(a['t_err_pct'], 8, 3)} {fmt(a['r_err_deg_per_100m'], 12, 3)} "
                 f"{fmt(a['ate_m'], 9, 3)} {fmt(a['rpe_m'], 8, 4)} {fmt(a['rpe_deg'], 8, 4)}")
    lines.append(f"(average over {', '.join(a['sequences']) or 'none'})")
    for seq, r in result["sequences"].items():
        if r.get("scale_warning"):
            lines.append(f"WARNING {seq}: {r['scale_warning']}")
    return "\n".join(lines)
