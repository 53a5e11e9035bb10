"""Matplotlib (Agg) PNG plots: top view of GT vs prediction, and t_err / r_err vs segment length.

Convention:
    KITTI camera frame: x right, y down, z forward, so the top view plots ``x`` (horizontal) against ``z``.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def plot_trajectory(gt: np.ndarray | None, pred: np.ndarray, path: str | Path, title: str = "") -> Path:
    """Top view (x-z) of ``gt`` ``(N,4,4)`` (optional) and ``pred`` ``(N,4,4)``, saved as a PNG at ``path``."""
    pred = np.asarray(pred)
    if pred.ndim != 3 or pred.shape[1:] not in ((4, 4), (3, 4)):
        raise ValueError(f"pred poses must be (N,4,4), got {pred.shape}")
    fig, ax = plt.subplots(figsize=(6, 6))
    if gt is not None:
        gt = np.asarray(gt)
        ax.plot(gt[:, 0, 3], gt[:, 2, 3], "k-", label="ground truth")
        ax.plot(gt[0, 0, 3], gt[0, 2, 3], "ks", label="start")
    ax.plot(pred[:, 0, 3], pred[:, 2, 3], "r-", label="prediction")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("z [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend()
    ax.set_title(title)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100, bbox_inches="tight")
    plt.close(fig)
    return path


def plot_segment_errors(per_length: dict, path: str | Path, title: str = "") -> Path:
    """t_err (%) and r_err (deg/100 m) against segment length from an ``evaluate_trajectory`` breakdown."""
    lengths = [int(k) for k, v in per_length.items() if v["t_err_pct"] is not None]
    fig, (ax_t, ax_r) = plt.subplots(1, 2, figsize=(10, 4))
    ax_t.plot(lengths, [per_length[str(k)]["t_err_pct"] for k in lengths], "bo-")
    ax_r.plot(lengths, [per_length[str(k)]["r_err_deg_per_100m"] for k in lengths], "bo-")
    ax_t.set_xlabel("segment length [m]")
    ax_t.set_ylabel("translation error [%]")
    ax_r.set_xlabel("segment length [m]")
    ax_r.set_ylabel("rotation error [deg/100 m]")
    fig.suptitle(title)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100, bbox_inches="tight")
    plt.close(fig)
    return path
