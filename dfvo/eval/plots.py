"""Matplotlib (Agg) pictures that explain a run: the trajectory, a per-frame panel, and KITTI segment errors.

- ``trajectory.png`` (:func:`plot_trajectory`): top view; the ground truth underneath (thick, light), the
  prediction over it; start and end marked; equal axes; the alignment and the metrics in the caption; without
  ground truth a scale bar in the trajectory's units, so a path of millimetres still reads as a path.
- ``frames.png`` (:func:`plot_frames`): per frame, the translation length and rotation angle of the relative motion
  (prediction vs ground truth), correspondences and inliers, the tracker used (a coloured band) and the fallbacks
  (shaded in every panel, reasons counted in the caption).
- ``*_segment_errors.png`` (:func:`plot_segment_errors`): t_err / r_err against KITTI segment length, written only
  when a segment exists (a path of at least 100 m); otherwise no file (a stale one is removed) and None returned.

Each ``plot_*`` saves a PNG and returns its path; the ``*_figure`` functions return the open figure (for tests and
notebooks; close it with ``plt.close(fig)``).

Convention:
    Poses ``(N,4,4)`` ``T_w_c`` (KITTI). KITTI camera frame: x right, y down, z forward, so the top view plots ``x``
    (horizontal) against ``z`` (``plane="xz"``). Per-frame motion at frame k is ``T_prev_cur = inv(T_w_{k-1}) @
    T_w_k``. Non-finite poses (frames without a prediction) leave gaps.
"""

from __future__ import annotations

import functools
import logging
import textwrap
from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib import font_manager  # noqa: E402
from matplotlib.colors import ListedColormap  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from matplotlib.patches import Patch  # noqa: E402
from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar  # noqa: E402

__all__ = ["plot_trajectory", "trajectory_figure", "plot_frames", "frames_figure", "plot_segment_errors",
           "segment_errors_figure", "ALIGN_DESCRIPTIONS", "TRACKER_COLORS"]

log = logging.getLogger(__name__)

ALIGN_DESCRIPTIONS = {"7dof": "7-DoF Sim(3) (rotation, translation, scale)", "6dof": "6-DoF SE(3) (rotation, "
                      "translation; predicted scale kept)", "scale": "scale only", "none": "none (as predicted)"}
TRACKER_COLORS = {"init": "#bbbbbb", "E": "#2ca02c", "PnP": "#ff7f0e", "constant_motion": "#d62728"}
_OTHER_COLOR = "#9467bd"
_MAX_REASONS = 6  # distinct fallback reasons listed under frames.png (the most frequent first)
_METRIC_FORMATS = (("t_err_pct", "t_err {:.2f} %"), ("r_err_deg_per_100m", "r_err {:.2f} deg/100 m"),
                   ("ate_m", "ATE {:.3g} m"), ("rpe_m", "RPE {:.3g} m"), ("rpe_deg", "RPE {:.3g} deg"))
_AXES = {"x": 0, "y": 1, "z": 2}


def _poses(x: Any, name: str) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    if a.ndim != 3 or a.shape[1:] not in ((4, 4), (3, 4)):
        raise ValueError(f"{name} poses must be (N,4,4), got {a.shape}")
    return a


def _save(fig: Figure, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


@functools.lru_cache(maxsize=64)
def _font_chars(path: str) -> frozenset[int]:
    from matplotlib.ft2font import FT2Font

    return frozenset(FT2Font(path).get_charmap())


@functools.lru_cache(maxsize=64)
def _font_having(chars: frozenset[str]) -> str | None:
    """The family name of an installed font that has every character of ``chars`` (None: no font has them).
    Matplotlib's "Last Resort" font does not count: it maps every character to the same placeholder box."""
    for entry in font_manager.fontManager.ttflist:
        if entry.name.startswith("Last Resort"):
            continue
        try:
            if all(ord(c) in _font_chars(entry.fname) for c in chars):
                return entry.name
        except (OSError, RuntimeError):  # a font file FreeType cannot open
            continue
    return None


def _drawable(text: str, family: str = "sans-serif") -> tuple[str, dict[str, Any]]:
    """``text`` and the Text keywords that draw it without matplotlib's "Glyph missing" warnings: characters the
    default font lacks (a sequence named in Chinese, Cyrillic, ...) are drawn with an installed font that has them
    (as a fallback family), else written as ASCII escapes (``\\u6771``)."""
    if text.isascii():
        return text, {}
    default = font_manager.findfont(font_manager.FontProperties(family=[family]))
    missing = frozenset(c for c in text if not c.isspace() and ord(c) not in _font_chars(default))
    if not missing:
        return text, {}
    fallback = _font_having(missing)
    if fallback is not None:
        return text, {"fontfamily": [font_manager.FontProperties(fname=default).get_name(), fallback]}
    return "".join(c.encode("ascii", "backslashreplace").decode() if c in missing else c for c in text), {}


def _nice_length(extent: float) -> float:
    """A round length (1, 2 or 5 x 10^k) near a fifth of ``extent``."""
    target = extent / 5.0
    k = np.floor(np.log10(target))
    return float(min((m * 10.0**k for m in (1, 2, 5, 10)), key=lambda v: abs(np.log(v / target))))


def _length_label(length: float, units: str) -> str:
    text = f"{length:g} {units}"
    if units == "m" and length < 0.01:
        text += f" ({length * 1000:g} mm)"
    elif units == "m" and length < 1:
        text += f" ({length * 100:g} cm)"
    return text


def _path_length(xyz: np.ndarray) -> float:
    steps = np.linalg.norm(np.diff(xyz, axis=0), axis=1)
    return float(np.nansum(steps))


def _caption(metrics: dict | None, align: str | None, caption: str | None, extra: str) -> str:
    parts = []
    if align is not None:
        parts.append(f"prediction aligned to ground truth: {ALIGN_DESCRIPTIONS.get(align, align)}")
    if metrics:
        vals = [fmt.format(metrics[k]) for k, fmt in _METRIC_FORMATS if isinstance(metrics.get(k), int | float)]
        if metrics.get("t_err_pct", 0) is None:
            vals.insert(0, "t_err/r_err n/a (no 100 m segment)")
        if vals:
            parts.append(" | ".join(vals))
    parts += [p for p in (extra, caption) if p]
    return "\n".join(textwrap.fill(p, 110) for p in parts)


def trajectory_figure(gt: np.ndarray | None, pred: np.ndarray, title: str = "", *, align: str | None = None,
                      metrics: dict | None = None, caption: str | None = None, units: str = "m",
                      plane: str = "xz") -> Figure:
    """Top view of ``gt`` (optional) and ``pred``; see :func:`plot_trajectory`. Returns the open figure."""
    pred = _poses(pred, "pred")
    if len(plane) != 2 or not set(plane) <= set(_AXES) or plane[0] == plane[1]:
        raise ValueError(f"plane={plane!r}: expected two of x, y, z such as 'xz'")
    ih, iv = _AXES[plane[0]], _AXES[plane[1]]
    fig, ax = plt.subplots(figsize=(7, 7))
    p = pred[:, :3, 3]
    finite = np.flatnonzero(np.isfinite(p).all(axis=1))
    if gt is not None:
        g = _poses(gt, "gt")[:, :3, 3]
        ax.plot(g[:, ih], g[:, iv], "-", color="0.72", lw=5, solid_capstyle="round", label="ground truth", zorder=1)
        ax.plot(g[-1, ih], g[-1, iv], "s", mfc="none", mec="0.45", ms=11, mew=2, label="end (ground truth)",
                zorder=4)
    ax.plot(p[:, ih], p[:, iv], "-", color="tab:blue", lw=1.6, label="prediction", zorder=3)
    if len(finite):
        a, b = finite[0], finite[-1]
        ax.plot(p[a, ih], p[a, iv], "o", color="tab:green", mec="k", ms=10, label="start", zorder=5)
        ax.plot(p[b, ih], p[b, iv], "s", color="tab:red", mec="k", ms=8, label="end (prediction)", zorder=5)
    ax.set_xlabel(f"{plane[0]} [{units}]")
    ax.set_ylabel(f"{plane[1]} [{units}]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, color="0.92")
    label, font = _drawable(title)
    ax.set_title(label, **font)
    ax.legend(loc="best", fontsize=8)
    length = _path_length(p[finite]) if len(finite) else 0.0
    extra = f"predicted path length {length:.4g} {units}, {len(pred)} frames"
    if gt is None:
        pts = p[finite][:, [ih, iv]]
        extent = float(np.max(np.ptp(pts, axis=0))) if len(pts) else 0.0
        if extent > 0:
            bar_len = _nice_length(extent)
            bar = AnchoredSizeBar(ax.transData, bar_len, _length_label(bar_len, units), "lower right", pad=0.5,
                                  sep=4, frameon=True, size_vertical=extent / 150, color="k")
            bar.set_gid("scale_bar")
            ax.add_artist(bar)
        else:
            ax.margins(0.5)
        extra += f"; no ground truth: axes and scale bar in the trajectory's units ({units})"
        if extent == 0:
            extra += "; the camera did not move"
    text = _caption(metrics, align, caption, extra)
    if text:
        text, font = _drawable(text)
        t = fig.text(0.5, 0.0, text, ha="center", va="top", fontsize=8.5, **font)
        t.set_gid("caption")
    return fig


def plot_trajectory(gt: np.ndarray | None, pred: np.ndarray, path: str | Path, title: str = "", *,
                    align: str | None = None, metrics: dict | None = None, caption: str | None = None,
                    units: str = "m", plane: str = "xz") -> Path:
    """Top view of ``gt`` (optional, drawn underneath) and ``pred``, saved as a PNG at ``path``.

    Args:
        gt: ``(N,4,4)`` ground-truth ``T_w_c`` or None (own video): then a scale bar is drawn.
        pred: ``(M,4,4)`` predicted ``T_w_c`` as it should be seen (already aligned when ``gt`` is given).
        path: PNG to write.
        title: figure title (e.g. the sequence).
        align: the alignment that was applied to ``pred`` (``7dof``, ``6dof``, ``scale``, ``none``), for the caption.
        metrics: an ``evaluate_trajectory`` dict; t_err, r_err, ATE, RPE go into the caption.
        caption: more text for the caption.
        units: length unit of the poses (``m``; say ``units`` for an up-to-scale monocular run).
        plane: the two axes shown, horizontal then vertical (``xz``: KITTI's top view).
    """
    return _save(trajectory_figure(gt, pred, title, align=align, metrics=metrics, caption=caption, units=units,
                                   plane=plane), path)


# ------------------------------------------------------------------------------------------------ per-frame panel
def _num(v: Any) -> float:
    if v is None or (isinstance(v, str) and v.strip() in ("", "None", "nan")):
        return float("nan")
    if isinstance(v, str) and v.strip().lower() in ("true", "false"):
        return float(v.strip().lower() == "true")
    try:
        return float(v)
    except (TypeError, ValueError):
        return float("nan")


def _flag(v: Any) -> bool:
    f = _num(v)
    return bool(f == f and f != 0)


def _relative_motion(poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Translation length and rotation angle (deg) of ``T_prev_cur`` for frames 1..N-1."""
    P = _poses(poses, "poses")
    if P.shape[1] == 3:
        P = np.concatenate([P, np.tile([[[0.0, 0.0, 0.0, 1.0]]], (len(P), 1, 1))], axis=1)
    rel = np.linalg.inv(P[:-1]) @ P[1:]
    tr = rel[:, 0, 0] + rel[:, 1, 1] + rel[:, 2, 2]
    return np.linalg.norm(rel[:, :3, 3], axis=1), np.degrees(np.arccos(np.clip(0.5 * (tr - 1.0), -1.0, 1.0)))


def frames_figure(rows: Sequence[dict[str, Any]], pred: np.ndarray | None = None, gt: np.ndarray | None = None,
                  title: str = "", units: str = "m") -> Figure:
    """The per-frame panel; see :func:`plot_frames`. Returns the open figure."""
    if not rows:
        raise ValueError("plot_frames: no per-frame rows (frames.csv is empty)")
    frames = np.array([int(_num(r.get("frame", i))) for i, r in enumerate(rows)])
    trackers = [str(r.get("tracker") or "") for r in rows]
    # a fallback is what summary.json counts: constant motion, or a PnP that failed; a frame whose E was set aside
    # for PnP (model selection, a gate) has a reason too, listed in the caption, but its tracker measured the pose
    noted = np.array([str(r.get("fallback_reason") or "").strip() not in ("", "None") for r in rows])
    constant = np.array([_flag(r.get("constant_motion")) or str(r.get("tracker")) == "constant_motion" for r in rows])
    pnp_failed = np.array([_flag(r.get("pnp_failed")) for r in rows])
    fallback = constant | pnp_failed
    fig, axes = plt.subplots(4, 1, figsize=(11, 9), sharex=True, gridspec_kw={"height_ratios": [3, 3, 2.2, 0.8]})
    ax_t, ax_r, ax_n, ax_k = axes
    for ax, gid in zip(axes, ("translation", "rotation", "correspondences", "tracker"), strict=True):
        ax.set_gid(gid)
        for f in frames[fallback]:
            ax.axvspan(f - 0.5, f + 0.5, color="tab:red", alpha=0.13, lw=0, zorder=0)
    if gt is not None:
        t_gt, r_gt = _relative_motion(gt)
        k = np.arange(1, len(t_gt) + 1)
        ax_t.plot(k, t_gt, "-", color="0.6", lw=3.5, label="ground truth", zorder=1)
        ax_r.plot(k, r_gt, "-", color="0.6", lw=3.5, label="ground truth", zorder=1)
    if pred is not None:
        t_p, r_p = _relative_motion(pred)
        k = np.arange(1, len(t_p) + 1)
        ax_t.plot(k, t_p, "-", color="tab:blue", lw=1.2, label="prediction", zorder=2)
        ax_r.plot(k, r_p, "-", color="tab:blue", lw=1.2, label="prediction", zorder=2)
    else:
        ax_t.plot(frames, [_num(r.get("scale")) for r in rows], ".-", color="tab:blue", lw=1.0,
                  label="scale (frames.csv)", zorder=2)
    ax_t.set_ylabel(f"translation\nper frame [{units}]")
    ax_r.set_ylabel("rotation\nper frame [deg]")
    n_corr = [_num(r.get("num_correspondences")) for r in rows]
    n_inl = [_num(r.get("num_inliers")) for r in rows]
    ax_n.plot(frames, n_corr, "-", color="tab:gray", lw=1.0, label="correspondences")
    ax_n.plot(frames, n_inl, "-", color="tab:purple", lw=1.2, label="inliers")
    ax_n.set_ylabel("count")
    ax_n.set_ylim(bottom=0)
    names = list(TRACKER_COLORS) + sorted({t for t in trackers if t and t not in TRACKER_COLORS})
    colors = [TRACKER_COLORS.get(n, _OTHER_COLOR) for n in names] + ["white"]
    code = np.array([names.index(t) if t in names else len(names) for t in trackers])
    order = np.argsort(frames, kind="stable")
    band = np.full(int(frames.max() - frames.min() + 1), len(names))
    band[frames[order] - frames.min()] = code[order]
    img = ax_k.imshow(band[None], aspect="auto", interpolation="nearest", cmap=ListedColormap(colors),
                      vmin=-0.5, vmax=len(names) + 0.5, extent=(frames.min() - 0.5, frames.max() + 0.5, 0, 1))
    img.set_gid("tracker_band")
    if fallback.any():
        ax_k.plot(frames[fallback], np.full(fallback.sum(), 0.5), "v", color="k", ms=5, label="fallback")
    ax_k.set_yticks([])
    ax_k.set_ylabel("tracker")
    ax_k.set_xlabel("frame")
    used = [n for n in names if n in trackers]
    handles = [Patch(color=TRACKER_COLORS.get(n, _OTHER_COLOR), label=n) for n in used]
    handles.append(Patch(color="tab:red", alpha=0.25, label="fallback frame"))
    if fallback.any():
        handles.append(ax_k.get_legend_handles_labels()[0][0])
    ax_k.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.0, 1.6), fontsize=8, frameon=False)
    for ax in (ax_t, ax_r, ax_n):
        ax.grid(True, color="0.92")
        if ax.get_legend_handles_labels()[0]:
            ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize=8, frameon=False)
    label, font = _drawable(title)
    ax_t.set_title(label, **font)
    count = Counter(t for t in trackers if t)
    reasons = Counter(str(r.get("fallback_reason")).strip() for r, on in zip(rows, noted, strict=True) if on)
    tracked = int((frames > 0).sum())
    text = "trackers: " + ", ".join(f"{n} {c}" for n, c in count.most_common())
    text += f" | fallback frames (as summary.json counts them): constant motion {int(constant.sum())} of {tracked}"
    text += f", PnP failed {int(pnp_failed.sum())}" if pnp_failed.any() else ""
    lines = textwrap.wrap(text, 130)
    if reasons:  # a legend table: one whole reason per line (wrapped, never cut), its frame count first
        lines.append("reasons noted, fallbacks and a tracker set aside for another (frames with that reason):")
        for reason, c in reasons.most_common(_MAX_REASONS):
            lines += textwrap.wrap(reason, 130, initial_indent=f"{c:>5} x  ", subsequent_indent=" " * 9)
        if len(reasons) > _MAX_REASONS:
            rest = sum(c for _, c in reasons.most_common()[_MAX_REASONS:])
            lines.append(f"{rest:>5} x  {len(reasons) - _MAX_REASONS} other reasons (every frame's reason: "
                         "frames.csv)")
    text, font = _drawable("\n".join(lines), "monospace" if reasons else "sans-serif")
    table = {"ha": "left", "family": "monospace"} if reasons else {"ha": "center"}
    fig.text(0.02 if reasons else 0.5, 0.0, text, va="top", fontsize=8.5, **{**table, **font}).set_gid("caption")
    fig.tight_layout()
    return fig


def plot_frames(rows: Sequence[dict[str, Any]], path: str | Path, pred: np.ndarray | None = None,
                gt: np.ndarray | None = None, title: str = "", units: str = "m") -> Path:
    """Per-frame panel ``frames.png``: where a run went wrong.

    Args:
        rows: per-frame rows as written to ``frames.csv`` (dicts; values may be the CSV's strings): ``frame``,
            ``tracker``, ``num_correspondences``, ``num_inliers``, ``scale``, ``fallback_reason``,
            ``constant_motion``, ``pnp_failed``. A frame falls back when it has a fallback reason, repeated the
            previous motion or PnP failed.
        path: PNG to write.
        pred: ``(N,4,4)`` predicted ``T_w_c`` (aligned like the trajectory plot, so lengths compare with ``gt``);
            without it the ``scale`` column is shown as the translation.
        gt: ``(N,4,4)`` ground truth or None.
        title: figure title.
        units: length unit of the poses.
    """
    return _save(frames_figure(rows, pred, gt, title, units), path)


# ------------------------------------------------------------------------------------------------ segment errors
def segment_errors_figure(per_length: dict, title: str = "") -> Figure | None:
    """t_err / r_err against segment length; None when no length has a segment. See :func:`plot_segment_errors`."""
    lengths = sorted(int(k) for k, v in per_length.items() if v.get("t_err_pct") is not None)
    if not lengths:
        return None
    rows = [per_length[str(k)] for k in lengths]
    counts = np.array([r.get("num_segments") or 0 for r in rows], dtype=float)
    fig, (ax_t, ax_r) = plt.subplots(1, 2, figsize=(10, 4))
    for ax, key, ylabel in ((ax_t, "t_err_pct", "translation error [%]"),
                            (ax_r, "r_err_deg_per_100m", "rotation error [deg/100 m]")):
        vals = np.array([r[key] for r in rows], dtype=float)
        ax.plot(lengths, vals, "o-", color="tab:blue", label="per segment length")
        if counts.sum() > 0:
            mean = float(np.sum(vals * counts) / counts.sum())
            ax.axhline(mean, color="tab:red", ls="--", lw=1, label=f"all segments: {mean:.3g}")
        for x, y, n in zip(lengths, vals, counts, strict=True):
            ax.annotate(f"n={int(n)}", (x, y), textcoords="offset points", xytext=(0, 6), ha="center", fontsize=7)
        ax.set_xlabel("segment length [m]")
        ax.set_ylabel(ylabel)
        ax.set_ylim(bottom=0)
        ax.grid(True, color="0.92")
        ax.legend(fontsize=8)
    text, font = _drawable(title)
    fig.suptitle(text, **font)
    return fig


def plot_segment_errors(per_length: dict, path: str | Path, title: str = "") -> Path | None:
    """KITTI t_err (%) and r_err (deg/100 m) against segment length, from ``evaluate_trajectory(...)["per_length"]``.

    Written only when at least one segment exists (a path of 100 m or more). Otherwise no PNG is written, a stale
    one at ``path`` is removed (a plot must never describe another run), one INFO line is logged, and None is
    returned: the trajectory plot's caption already says "t_err/r_err n/a (no 100 m segment)".
    """
    fig = segment_errors_figure(per_length, title)
    path = Path(path)
    if fig is None:
        if path.is_file():
            path.unlink()
        log.info("no segment-error plot %s: no KITTI segment (the path is shorter than 100 m)", path)
        return None
    return _save(fig, path)
