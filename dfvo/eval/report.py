"""Odometry evaluation of trajectory files or folders of them: per-sequence metrics, the average, a text table.

Convention:
    A sequence is a pair of files: ``pred_dir/<seq>.<ext>`` and ``gt_dir/<seq>.<ext>`` (``ext`` one of
    :data:`TRAJECTORY_SUFFIXES`), or ``gt_dir/<seq>/`` as a dataset folder (EuRoC ``mav0/``, TUM RGB-D
    ``groundtruth.txt``); or two single files. Files are read in ``format`` (``auto`` by content) and paired by
    :func:`dfvo.io.association.associate_trajectories`; how they were paired is stated per sequence. The
    ``average`` entry is the plain mean over sequences (not weighted by length) of each metric that has a value;
    sequences listed in ``exclude`` stay in the per-sequence output but not in the average.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from dfvo.eval.alignment import AlignMode
from dfvo.eval.odometry_metrics import aligned_prediction, evaluate_trajectory
from dfvo.io.association import associate_trajectories
from dfvo.io.trajectory import (
    FORMATS,
    Trajectory,
    detect_format,
    read_times,
    read_trajectory,
    resolve_trajectory_file,
)
from dfvo.validation import choice

SUMMARY_KEYS = ("t_err_pct", "r_err_deg_per_100m", "ate_m", "rpe_m", "rpe_deg")
TRAJECTORY_SUFFIXES = (".txt", ".tum", ".csv")


def sequence_name(seq: object) -> str:
    """KITTI sequence name of ``seq``: integer ids get two digits (``6`` -> ``"06"``), other names are kept
    (the rule :class:`dfvo.data.kitti_odometry.KittiOdometry` applies to ``infer.py seq=...``)."""
    text = str(seq)
    return text.zfill(2) if text.isdigit() else text


def _file_of(folder: Path, seq: str, what: str, dataset_folder: bool = False) -> Path:
    found = [folder / f"{seq}{ext}" for ext in TRAJECTORY_SUFFIXES if (folder / f"{seq}{ext}").is_file()]
    if len(found) > 1:
        raise ValueError(f"{what}={folder}: sequence {seq} has several files ({', '.join(p.name for p in found)}); "
                         "keep one")
    if found:
        return found[0]
    if dataset_folder and (folder / seq).is_dir():
        return resolve_trajectory_file(folder / seq)
    raise FileNotFoundError(f"{what}={folder}: no trajectory file for sequence {seq} ({folder / f'{seq}.txt'}, "
                            f"{' or '.join(seq + e for e in TRAJECTORY_SUFFIXES[1:])})")


def find_sequences(gt: str | Path, pred: str | Path, seqs: list[str] | None = None) -> dict[str, tuple[Path, Path]]:
    """``{seq: (gt_file, pred_file)}`` for two folders, or for two files (then ``seq`` is the prediction's stem)."""
    gt, pred = Path(gt), Path(pred)
    if not pred.exists():
        raise FileNotFoundError(f"prediction {pred} does not exist")
    if not gt.exists():
        raise FileNotFoundError(f"ground truth {gt} does not exist")
    if pred.is_file():
        if gt.is_dir():
            try:
                return {pred.stem: (resolve_trajectory_file(gt), pred)}  # a dataset folder
            except FileNotFoundError:
                return {pred.stem: (_file_of(gt, pred.stem, "gt_dir", dataset_folder=True), pred)}
        return {pred.stem: (gt, pred)}
    if gt.is_file():
        raise ValueError(f"gt={gt} is a file but pred={pred} is a folder; give two files or two folders")
    if seqs is None:
        stems = sorted({p.stem for p in pred.iterdir() if p.is_file() and p.suffix in TRAJECTORY_SUFFIXES})
        out = {}
        for s in stems:
            try:
                out[s] = (_file_of(gt, s, "gt_dir", dataset_folder=True), _file_of(pred, s, "pred_dir"))
            except FileNotFoundError:
                continue
        if not out:
            raise FileNotFoundError(f"no trajectory file in pred_dir={pred} has a matching one in gt_dir={gt}")
        return out
    return {s: (_file_of(gt, s, "gt_dir", dataset_folder=True), _file_of(pred, s, "pred_dir")) for s in seqs}


def _times_file(gt_times: Path, seq: str) -> Path:
    if gt_times.is_file():
        return gt_times
    for cand in (gt_times / f"{seq}.txt", gt_times / "sequences" / seq / "times.txt", gt_times / seq / "times.txt"):
        if cand.is_file():
            return cand
    raise FileNotFoundError(f"gt_times={gt_times}: no timestamps for sequence {seq} (looked for {seq}.txt, "
                            f"sequences/{seq}/times.txt, {seq}/times.txt)")


def read_pair(gt_file: Path, pred_file: Path, format: str = "auto", gt_format: str | None = None,
              gt_times: str | Path | None = None, seq: str = "") -> tuple[Trajectory, Trajectory, str, str]:
    """Read a ground-truth and a predicted trajectory; returns ``(gt, pred, gt_format, pred_format)``."""
    gt_fmt = gt_format or format
    for key, value in (("format", format), ("gt_format", gt_fmt)):
        if value not in FORMATS:
            raise ValueError(f"{key}={value!r}: expected one of {FORMATS}")
    gt_fmt = detect_format(gt_file) if gt_fmt == "auto" else gt_fmt
    pred_fmt = detect_format(pred_file) if format == "auto" else format
    gt, pred = read_trajectory(gt_file, gt_fmt), read_trajectory(pred_file, pred_fmt)
    if gt_times is not None:
        times_path = _times_file(Path(gt_times), seq)
        times = read_times(times_path)
        ids = gt.frame_ids if gt.frame_ids is not None else np.arange(len(gt))
        if (gt.frame_ids is None and len(times) != len(gt)) or ids.max() >= len(times):
            raise ValueError(f"gt_times={times_path} has {len(times)} timestamps but {gt_file} has {len(gt)} poses "
                             f"(frames up to {ids.max()}); expected one timestamp per frame")
        gt = Trajectory(gt.poses, times[ids], gt.frame_ids, gt.source)
    return gt, pred, gt_fmt, pred_fmt


def infer_run_align(pred: str | Path) -> tuple[str | None, Path]:
    """``(align, metrics.json)``: the alignment ``infer.py`` wrote into the ``metrics.json`` beside the predictions
    ``pred`` (a file or a folder), None when there is none (or it is not readable)."""
    folder = Path(pred) if Path(pred).is_dir() else Path(pred).parent
    path = folder / "metrics.json"
    try:
        return choice(AlignMode, json.loads(path.read_text()).get("align"), "align").value, path
    except (OSError, ValueError, AttributeError, TypeError):
        return None, path


def resolve_align(align: str, pred: str | Path) -> str:
    """The alignment mode of ``align`` (:class:`~dfvo.eval.alignment.AlignMode` or ``auto``) for the predictions at
    ``pred``: ``auto`` is the alignment ``infer.py`` used when they are an ``infer.py`` run's
    (:func:`infer_run_align`), so that a run evaluated again reads as its own report; else ``7dof``, the usual
    alignment of a monocular trajectory."""
    if str(align) != "auto":
        return choice(AlignMode, align, "align").value
    return infer_run_align(pred)[0] or AlignMode.sim3.value


def evaluate_sequences(gt_dir: str | Path, pred_dir: str | Path, seqs: list[str] | None = None, align: str = "auto",
                       exclude: list[str] | None = None, plot_dir: str | Path | None = None, *, format: str = "auto",
                       gt_format: str | None = None, allow_prefix: bool = False, max_time_diff: float = 0.01,
                       time_offset: float = 0.0, gt_times: str | Path | None = None) -> dict:
    """Evaluate each predicted trajectory against its ground truth.

    Args:
        gt_dir: folder of ground-truth files (or one file / dataset folder when ``pred_dir`` is a file).
        pred_dir: folder of predicted files, e.g. ``infer.py``'s ``out_dir`` (or one file).
        seqs: sequence names such as ``["09", "10"]``; None = every trajectory file of ``pred_dir`` with GT.
        align: ``auto`` | ``6dof`` | ``7dof`` | ``scale`` | ``none`` (``auto``: :func:`resolve_align`).
        exclude: sequences left out of the average (e.g. ``["01"]`` as in the DF-VO paper).
        plot_dir: when set, writes ``<seq>_trajectory.png`` and ``<seq>_segment_errors.png`` there.
        format: ``auto`` | ``kitti`` | ``tum`` | ``euroc`` for the predictions (and the GT unless ``gt_format``).
        gt_format: format of the ground truth (None: ``format``).
        allow_prefix: evaluate a shorter line-by-line prediction against the first poses of the GT.
        max_time_diff: timestamp association tolerance (s); time_offset: added to predicted timestamps (s).
        gt_times: a ``times.txt`` giving the GT file timestamps (or a folder holding ``<seq>.txt`` or
            ``sequences/<seq>/times.txt``).

    Returns:
        ``{"align", "sequences": {seq: evaluate_trajectory dict + "gt_file", "pred_file", "gt_format",
        "pred_format", "association"}, "average": {..., "sequences": [...]}}``.
    """
    align = resolve_align(align, pred_dir)
    pairs = find_sequences(gt_dir, pred_dir, [sequence_name(s) for s in seqs] if seqs is not None else None)
    results = {}
    for seq, (gt_file, pred_file) in pairs.items():
        gt, pred, gt_fmt, pred_fmt = read_pair(gt_file, pred_file, format, gt_format, gt_times, seq)
        assoc = associate_trajectories(gt, pred, max_time_diff, time_offset, allow_prefix)
        res = evaluate_trajectory(assoc.gt, assoc.pred, align=align, valid=assoc.valid)
        res.update(gt_file=str(gt_file), pred_file=str(pred_file), gt_format=gt_fmt, pred_format=pred_fmt,
                   association=assoc.as_dict())
        results[seq] = res
        if plot_dir is not None:
            from dfvo.eval.plots import plot_segment_errors, plot_trajectory  # deferred: matplotlib, only for plots

            gt0, _, aligned, _ = aligned_prediction(assoc.gt, assoc.pred, align, assoc.valid)
            plot_trajectory(gt0, aligned[assoc.valid], Path(plot_dir) / f"{seq}_trajectory.png",
                            title=f"{seq} (align={align})")
            plot_segment_errors(res["per_length"], Path(plot_dir) / f"{seq}_segment_errors.png", title=seq)
    excluded = {sequence_name(e) for e in (exclude or [])}
    used = [s for s in results if s not in excluded]
    average: dict = {"sequences": used}
    for key in SUMMARY_KEYS:
        vals = [results[s][key] for s in used if results[s][key] is not None]
        average[key] = float(np.mean(vals)) if vals else None
    return {"align": align, "sequences": results, "average": average}


def format_table(result: dict) -> str:
    """A fixed-width text table of ``evaluate_sequences`` output (one row per sequence plus the average), then
    how each sequence's poses were paired when not line by line, and the scale warnings."""
    w = max([8, *(len(s) for s in result["sequences"])])
    head = f"{'seq':>{w}} {'frames':>7} {'t_err%':>8} {'r_err°/100m':>12} {'ATE m':>9} {'RPE m':>8} {'RPE °':>8}"
    lines = [f"alignment: {result['align']}", head, "-" * len(head)]

    def fmt(v, w, p):
        return f"{v:>{w}.{p}f}" if v is not None else f"{'-':>{w}}"

    for seq, r in result["sequences"].items():
        lines.append(f"{seq:>{w}} {r['num_frames']:>7d} {fmt(r['t_err_pct'], 8, 3)} "
                     f"{fmt(r['r_err_deg_per_100m'], 12, 3)} "
                     f"{fmt(r['ate_m'], 9, 3)} {fmt(r['rpe_m'], 8, 4)} {fmt(r['rpe_deg'], 8, 4)}")
    a = result["average"]
    lines.append("-" * len(head))
    lines.append(f"{'average':>{w}} {'':>7} {fmt(a['t_err_pct'], 8, 3)} {fmt(a['r_err_deg_per_100m'], 12, 3)} "
                 f"{fmt(a['ate_m'], 9, 3)} {fmt(a['rpe_m'], 8, 4)} {fmt(a['rpe_deg'], 8, 4)}")
    lines.append(f"(average over {', '.join(a['sequences']) or 'none'}; '-': no 100 m segment / no consecutive pair)")
    for seq, r in result["sequences"].items():
        assoc = r.get("association")
        if assoc and assoc["method"] != "order":
            lines.append(f"{seq}: {assoc['description']}")
    for seq, r in result["sequences"].items():
        if r.get("scale_warning"):
            lines.append(f"WARNING {seq}: {r['scale_warning']}")
    return "\n".join(lines)
