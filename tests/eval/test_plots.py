"""Plots that explain a run: what is drawn equals what was given (line data, markers, equal axes, scale bar,
caption), the per-frame panel from frames.csv rows, and segment plots only when segments exist."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import pytest

from dfvo.eval import evaluate_trajectory
from dfvo.eval.plots import (
    TRACKER_COLORS,
    frames_figure,
    plot_frames,
    plot_segment_errors,
    plot_trajectory,
    segment_errors_figure,
    trajectory_figure,
)

PNG = b"\x89PNG\r\n\x1a\n"


def _curve(n: int, step: float, yaw_rate: float = 0.02) -> np.ndarray:
    """(n,4,4) T_w_c driving forward ``step`` per frame while turning ``yaw_rate`` rad per frame about y."""
    poses = np.tile(np.eye(4), (n, 1, 1))
    for k in range(1, n):
        c, s = math.cos(yaw_rate), math.sin(yaw_rate)
        rel = np.eye(4)
        rel[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
        rel[2, 3] = step
        poses[k] = poses[k - 1] @ rel
    return poses


def _line(ax: plt.Axes, label: str) -> plt.Line2D:
    lines = [ln for ln in ax.get_lines() if ln.get_label() == label]
    assert len(lines) == 1, [ln.get_label() for ln in ax.get_lines()]
    return lines[0]


def _caption(fig: plt.Figure) -> str:
    return next(t.get_text() for t in fig.texts if t.get_gid() == "caption")


def _equal_scale(ax: plt.Axes) -> bool:
    ax.figure.canvas.draw()
    (x0, y0), (x1, y1) = ax.transData.transform([[0.0, 0.0], [1.0, 1.0]])
    return math.isclose(abs(x1 - x0), abs(y1 - y0), rel_tol=1e-6)


def test_trajectory_draws_both_paths_markers_and_caption(tmp_path: Path) -> None:
    gt = _curve(200, 1.0)
    pred = gt.copy()
    pred[:, 0, 3] += np.linspace(0, 4, 200)
    metrics = evaluate_trajectory(gt, pred, "7dof")
    fig = trajectory_figure(gt, pred, "seq", align="7dof", metrics=metrics)
    ax = fig.axes[0]
    g, p = _line(ax, "ground truth"), _line(ax, "prediction")
    np.testing.assert_array_equal(g.get_xdata(), gt[:, 0, 3])
    np.testing.assert_array_equal(g.get_ydata(), gt[:, 2, 3])
    np.testing.assert_array_equal(p.get_xdata(), pred[:, 0, 3])
    np.testing.assert_array_equal(p.get_ydata(), pred[:, 2, 3])
    assert g.get_zorder() < p.get_zorder() and g.get_linewidth() > 2 * p.get_linewidth()  # GT under, wider
    assert (_line(ax, "start").get_xdata()[0], _line(ax, "start").get_ydata()[0]) == (pred[0, 0, 3], pred[0, 2, 3])
    assert _line(ax, "end (prediction)").get_xdata()[0] == pred[-1, 0, 3]
    assert _line(ax, "end (ground truth)").get_ydata()[0] == gt[-1, 2, 3]
    assert ax.get_aspect() == 1.0 and _equal_scale(ax)
    text = _caption(fig)
    assert "7-DoF Sim(3)" in text and f"t_err {metrics['t_err_pct']:.2f} %" in text
    assert f"ATE {metrics['ate_m']:.3g} m" in text and "200 frames" in text
    assert not [a for a in ax.artists if a.get_gid() == "scale_bar"]  # metres from the ground truth: no bar
    plt.close(fig)
    out = plot_trajectory(gt, pred, tmp_path / "sub" / "trajectory.png", "seq", align="7dof", metrics=metrics)
    assert out.read_bytes()[:8] == PNG and out.stat().st_size > 5000


def test_trajectory_without_gt_millimetres_reads_as_a_path(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    n = 80
    own = np.tile(np.eye(4), (n, 1, 1))
    own[:, 0, 3] = 0.004 * np.sin(np.linspace(0, 6, n)) + 0.0002 * rng.normal(size=n)
    own[:, 2, 3] = np.linspace(0, 0.012, n)
    fig = trajectory_figure(None, own, "own video")
    ax = fig.axes[0]
    bars = [a for a in ax.artists if a.get_gid() == "scale_bar"]
    assert len(bars) == 1
    # extent 12 mm -> a round bar of 2 mm, labelled in the trajectory's units
    label = [t.get_text() for t in bars[0].findobj(lambda o: hasattr(o, "get_text"))]
    assert "0.002 m (2 mm)" in label
    assert _line(ax, "start").get_xdata()[0] == own[0, 0, 3]
    assert ax.get_aspect() == 1.0 and _equal_scale(ax)
    assert "no ground truth" in _caption(fig) and "ground truth" not in [ln.get_label() for ln in ax.get_lines()]
    plt.close(fig)
    # a still camera: no bar, no crash, said in the caption
    fig = trajectory_figure(None, np.tile(np.eye(4), (5, 1, 1)))
    assert "did not move" in _caption(fig)
    plt.close(fig)
    with pytest.raises(ValueError, match="plane"):
        trajectory_figure(None, own, plane="xx")
    with pytest.raises(ValueError, match=r"pred poses must be \(N,4,4\)"):
        trajectory_figure(None, own[:, :2])


def _span_centre(patch) -> float:
    """x centre of an axvspan (a Rectangle since matplotlib 3.9, a Polygon before)."""
    if hasattr(patch, "get_width"):
        return patch.get_x() + patch.get_width() / 2
    return float(np.mean(np.asarray(patch.get_xy())[:, 0]))


def _rows_via_csv(tmp_path: Path, n: int) -> list[dict]:
    """frames.csv written as the pipeline does (DictWriter, blanks for None) and read back as strings."""
    rows = [{"frame": 0, "tracker": "init"}]
    for k in range(1, n):
        tracker, reason, cm = "E", None, False
        if k in (5, 6):
            tracker, reason = "PnP", "E: low cheirality"
        if k == 9:
            tracker, reason, cm = "constant_motion", "selection failed: too few", True
        rows.append({"frame": k, "tracker": tracker, "num_correspondences": 100 + k, "num_inliers": 50 + k,
                     "scale": 1.0, "fallback_reason": reason, "constant_motion": int(cm), "pnp_failed": 0})
    path = tmp_path / "frames.csv"
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["frame", "tracker", "num_correspondences", "num_inliers", "scale",
                                          "fallback_reason", "constant_motion", "pnp_failed"])
        w.writeheader()
        for r in rows:
            w.writerow({k: ("" if v is None else v) for k, v in r.items()})
    with path.open() as f:
        return list(csv.DictReader(f))


def test_frames_panel_shows_motion_inliers_trackers_and_fallbacks(tmp_path: Path) -> None:
    n = 12
    gt = _curve(n, 1.0, yaw_rate=math.radians(2.0))
    pred = _curve(n, 1.1, yaw_rate=math.radians(2.5))
    rows = _rows_via_csv(tmp_path, n)
    fig = frames_figure(rows, pred=pred, gt=gt, title="t")
    axes = {ax.get_gid(): ax for ax in fig.axes}
    ax_t, ax_r, ax_n, ax_k = (axes[k] for k in ("translation", "rotation", "correspondences", "tracker"))
    np.testing.assert_array_equal(_line(ax_t, "prediction").get_xdata(), np.arange(1, n))
    np.testing.assert_allclose(_line(ax_t, "prediction").get_ydata(), 1.1, rtol=1e-9)
    np.testing.assert_allclose(_line(ax_t, "ground truth").get_ydata(), 1.0, rtol=1e-9)
    np.testing.assert_allclose(_line(ax_r, "prediction").get_ydata(), 2.5, rtol=1e-6)
    np.testing.assert_allclose(_line(ax_r, "ground truth").get_ydata(), 2.0, rtol=1e-6)
    inl = _line(ax_n, "inliers")
    np.testing.assert_array_equal(inl.get_xdata(), np.arange(n))
    assert np.isnan(inl.get_ydata()[0]) and list(inl.get_ydata()[1:]) == [50.0 + k for k in range(1, n)]
    band = next(im for im in ax_k.get_images() if im.get_gid() == "tracker_band").get_array()[0]
    names = list(TRACKER_COLORS)
    assert [names[int(c)] for c in band] == [r["tracker"] for r in rows]
    # the fallback frame 9 (constant motion, as summary.json counts) shaded in every panel and marked in the band;
    # frames 5 and 6, where PnP measured the pose after E was set aside, are not fallbacks (issue 42: frames.png
    # counted them, "50 of 51" where summary.json said 31) but their reason is listed
    for ax in (ax_t, ax_r, ax_n, ax_k):
        spans = sorted(round(_span_centre(p)) for p in ax.patches)
        assert spans == [9], spans
    assert list(_line(ax_k, "fallback").get_xdata()) == [9]
    text = _caption(fig)
    assert "constant motion 1 of 11" in text and "    2 x  E: low cheirality" in text and "E 8" in text
    assert "    1 x  selection failed: too few" in text
    plt.close(fig)
    out = plot_frames(rows, tmp_path / "frames.png", pred=pred, gt=gt)
    assert out.read_bytes()[:8] == PNG and out.stat().st_size > 5000
    # without poses the scale column stands in for the translation; empty rows are refused
    fig = frames_figure(rows)
    axes = {ax.get_gid(): ax for ax in fig.axes}
    assert list(_line(axes["translation"], "scale (frames.csv)").get_ydata()[1:]) == [1.0] * (n - 1)
    plt.close(fig)
    with pytest.raises(ValueError, match="frames.csv is empty"):
        frames_figure([])


def test_segment_errors_only_when_segments_exist(tmp_path: Path) -> None:
    gt = _curve(400, 1.0, yaw_rate=0.005)
    pred = gt.copy()
    pred[:, :3, 3] *= np.linspace(1.0, 1.05, 400)[:, None]
    res = evaluate_trajectory(gt, pred, "none")
    fig = segment_errors_figure(res["per_length"], "long")
    ax_t = fig.axes[0]
    per = _line(ax_t, "per segment length")
    have = [int(k) for k, v in res["per_length"].items() if v["t_err_pct"] is not None]
    assert list(per.get_xdata()) == have == [100, 200, 300]
    np.testing.assert_allclose(per.get_ydata(), [res["per_length"][str(k)]["t_err_pct"] for k in have])
    mean = next(ln for ln in ax_t.get_lines() if ln.get_label().startswith("all segments"))
    assert mean.get_ydata()[0] == pytest.approx(res["t_err_pct"])  # weighted by segment count = the metric
    plt.close(fig)
    out = plot_segment_errors(res["per_length"], tmp_path / "seg.png", "long")
    assert out is not None and out.read_bytes()[:8] == PNG

    short = evaluate_trajectory(gt[:60], pred[:60], "none")
    assert short["t_err_pct"] is None
    stale = tmp_path / "short_segment_errors.png"
    stale.write_bytes(b"old plot of another run")
    assert segment_errors_figure(short["per_length"]) is None
    assert plot_segment_errors(short["per_length"], stale) is None and not stale.exists()
    assert plot_segment_errors(short["per_length"], tmp_path / "none.png") is None
    assert not (tmp_path / "none.png").exists()


def test_frames_caption_gives_whole_fallback_reasons() -> None:
    """Issue 28: the caption of frames.png lists each fallback reason whole (a legend table: count, then the reason,
    wrapped), never cut mid-number; beyond six distinct reasons the rest are counted."""
    long = ("selection failed: only 37 pixels with inconsistency < 0.1 px; valid pixels in only 3 of 100 regions, "
            "need >= 2 regions with 50 pixels each and >= 2000 correspondences in all")
    rows = [{"frame": 0, "tracker": "init"}]
    rows += [{"frame": k, "tracker": "constant_motion", "fallback_reason": long, "constant_motion": 1}
             for k in range(1, 12)]
    rows += [{"frame": 12 + k, "tracker": "PnP", "fallback_reason": f"reason number {k}"} for k in range(7)]
    fig = frames_figure(rows, title="t")
    text = _caption(fig)
    plt.close(fig)
    lines = text.splitlines()
    assert "reasons noted, fallbacks and a tracker set aside for another (frames with that reason):" in lines
    start = next(i for i, line in enumerate(lines) if line.startswith("   11 x  "))
    joined = " ".join(line.strip() for line in lines[start:start + 2]).removeprefix("11 x  ")
    assert joined == long, joined  # whole, over two wrapped lines
    assert all(len(line) <= 130 for line in lines)
    assert sum(line.startswith("    1 x  reason number") for line in lines) == 5
    assert lines[-1] == "    2 x  2 other reasons (every frame's reason: frames.csv)"


def test_non_latin_titles_draw_without_glyph_warnings(tmp_path: Path) -> None:
    """Issue 28: a sequence named in Chinese or Greek: the plots are written without matplotlib's "Glyph ... missing"
    warnings (an installed font that has the letters draws them, else they are written as escapes)."""
    import warnings

    from dfvo.eval.plots import _drawable

    title = "东京_Αθήνα_06"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        plot_trajectory(_curve(10, 1.0), _curve(10, 1.1), tmp_path / "t.png", title=title, align="7dof")
        plot_frames(_rows_via_csv(tmp_path, 10), tmp_path / "f.png", title=title)
        fig = segment_errors_figure({"100": {"t_err_pct": 1.0, "r_err_deg_per_100m": 0.5, "num_segments": 3}},
                                    title=title)
        fig.savefig(tmp_path / "s.png")
        plt.close(fig)
    glyphs = [str(w.message) for w in caught if "Glyph" in str(w.message)]
    assert not glyphs, glyphs
    text, font = _drawable(title)
    if font:  # a font with the letters is installed: the title is kept as it is
        assert text == title and len(font["fontfamily"]) == 2
    else:  # none: escapes for what DejaVu Sans lacks (it has Greek, not CJK)
        assert text == "\\u4e1c\\u4eac_Αθήνα_06", text
    assert _drawable("KITTI 06") == ("KITTI 06", {})
