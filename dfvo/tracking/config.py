"""Tracker configuration: every parameter of the odometry loop, with the official DF-VO defaults."""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["TrackerConfig"]

_CHOICES = {
    "tracker": ("hybrid", "e", "pnp"),
    "selection_method": ("local_best_k", "best_n", "uniform"),
    "scale_method": ("simple", "iterative"),
    "scale_depth_views": (1, 2),
    "model_selection": ("gric", "flow"),
}


@dataclass
class TrackerConfig:
    """All tracker settings (official defaults; see ``../shared/reference/official-defaults.md``).

    Attributes:
        tracker: "hybrid" (E-tracker, PnP fallback; paper), "e" (E only; constant motion when invalid),
            "pnp" (PnP only).
        selection_method, num_correspondences, grid, max_inconsistency, min_valid_fraction,
        min_region_fraction, selection_crop_top: correspondence selection (dfvo.matching.selection).
        e_threshold_px: essential RANSAC inlier threshold (pixels, converted to normalised coordinates).
        e_iterations: minimal samples per RANSAC repeat; ransac_repeats: repeats, most inliers wins.
        h_threshold_px, h_iterations: homography RANSAC for GRIC.
        min_correspondences: with this many or fewer valid correspondences E is invalid.
        min_cheirality_fraction: E invalid when fewer rows pass cheirality.
        model_selection: "gric" (E vs H) or "flow" (E when the median flow magnitude exceeds
            flow_magnitude_threshold pixels).
        gric_sigma: fixed residual standard deviation (pixels).
        scale_method: "simple" (1-D RANSAC on depth ratios) or "iterative" (paper Alg. 2).
        scale_depth_views: 1 (paper): the scale comes from the CNN depth of the earlier frame i; 2: also from the
            depth of the later frame j (its own 1-D RANSAC on depth ratios in camera j) and the two scales are
            combined by their geometric mean (one alone when the other fails). Our addition: per-frame errors of
            the CNN depth's scale are nearly independent from frame to frame, so two views halve their variance.
        scale_views_max_ratio: with two views, scales that differ by more than this factor are not averaged
            (one view is broken, e.g. a close object in only one frame); the earlier frame's scale is used.
        scale_min_points, scale_ransac_trials, scale_ransac_samples, scale_inlier_threshold: simple scale.
        iterative_max_iters, iterative_tol, iterative_flow_threshold_px: iterative scale.
        max_depth, depth_crop_top: depth used for scale/PnP lies in (0, max_depth] and below the top rows.
        pnp_threshold_px, pnp_iterations, pnp_min_points: PnP RANSAC.
        seed: base seed; frame k of a sequence draws from ``torch.Generator().manual_seed(seed + k)``.
    """

    tracker: str = "hybrid"
    selection_method: str = "local_best_k"
    num_correspondences: int = 2000
    grid: tuple[int, int] = (10, 10)
    max_inconsistency: float = 0.1
    min_valid_fraction: float = 0.1
    min_region_fraction: float = 0.1
    selection_crop_top: float = 0.0
    e_threshold_px: float = 0.2
    e_iterations: int = 20
    ransac_repeats: int = 5
    h_threshold_px: float = 1.0
    h_iterations: int = 50
    min_correspondences: int = 10
    min_cheirality_fraction: float = 0.1
    model_selection: str = "gric"
    gric_sigma: float = 0.8
    flow_magnitude_threshold: float = 5.0
    scale_method: str = "simple"
    scale_depth_views: int = 1
    scale_views_max_ratio: float = 1.5
    scale_min_points: int = 10
    scale_ransac_trials: int = 100
    scale_ransac_samples: int = 3
    scale_inlier_threshold: float = 0.1
    iterative_max_iters: int = 5
    iterative_tol: float = 1e-3
    iterative_flow_threshold_px: float = 5.0
    max_depth: float = 50.0
    depth_crop_top: float = 0.3
    pnp_threshold_px: float = 1.0
    pnp_iterations: int = 100
    pnp_min_points: int = 6
    seed: int = 0

    def __post_init__(self) -> None:
        for name, allowed in _CHOICES.items():
            if getattr(self, name) not in allowed:
                raise ValueError(f"TrackerConfig.{name}={getattr(self, name)!r}; expected one of {allowed}")
        self.grid = (int(self.grid[0]), int(self.grid[1]))
        for name in ("num_correspondences", "e_iterations", "ransac_repeats", "h_iterations", "scale_ransac_trials",
                     "iterative_max_iters", "pnp_iterations"):
            if int(getattr(self, name)) <= 0:
                raise ValueError(f"TrackerConfig.{name}={getattr(self, name)}; expected a positive integer")
        for name in ("e_threshold_px", "h_threshold_px", "gric_sigma", "max_depth", "pnp_threshold_px",
                     "scale_inlier_threshold"):
            if float(getattr(self, name)) <= 0:
                raise ValueError(f"TrackerConfig.{name}={getattr(self, name)}; expected > 0")
        if not float(self.scale_views_max_ratio) > 1.0:
            raise ValueError(f"TrackerConfig.scale_views_max_ratio={self.scale_views_max_ratio}; expected > 1")
        if not 0.0 <= self.depth_crop_top < 1.0 or not 0.0 <= self.selection_crop_top < 1.0:
            raise ValueError(f"TrackerConfig: depth_crop_top={self.depth_crop_top}, selection_crop_top="
                             f"{self.selection_crop_top}; expected fractions in [0, 1)")
