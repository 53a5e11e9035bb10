"""Tracker configuration: one typed node (``tracker`` in ``infer.py``'s config) with one section per stage.

This dataclass is the single home of every tracker default; the YAML files of the config groups ``tracker``,
``correspondence``, ``scale`` and ``model_selection`` (``dfvo/conf/infer/``) only select a choice (e.g.
``method: best_n``) and the command line overrides single values (``tracker.scale.depth_views=1``). The defaults are
what ``infer.py`` runs; where they differ from the paper / the authors' code, the field says so and
``experiment=paper`` restores the paper's configuration. Defaults read from the official implementation are in
``../shared/reference/official-defaults.md``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum, StrEnum

__all__ = ["TrackerMode", "SelectionMethod", "ModelSelectionMethod", "ScaleMethod", "SelectionConfig",
           "EssentialConfig", "ModelSelectionConfig", "ScaleConfig", "PnPConfig", "TrackerConfig"]


class TrackerMode(StrEnum):
    """Which trackers run: ``hybrid`` (E-tracker, PnP when E is unreliable; the paper), ``e`` (E only; constant
    motion when invalid), ``pnp`` (PnP only)."""

    hybrid = "hybrid"
    e = "e"
    pnp = "pnp"


class SelectionMethod(StrEnum):
    """Correspondence selection (:mod:`dfvo.matching.selection`)."""

    local_best_k = "local_best_k"
    best_n = "best_n"
    uniform = "uniform"


class ModelSelectionMethod(StrEnum):
    """E-vs-PnP decision: ``gric`` (E vs H) or ``flow`` (median flow magnitude)."""

    gric = "gric"
    flow = "flow"


class ScaleMethod(StrEnum):
    """Scale recovery: ``simple`` (1-D RANSAC on depth ratios) or ``iterative`` (paper Algorithm 2)."""

    simple = "simple"
    iterative = "iterative"


def _check(condition: bool, message: str) -> None:
    if not condition:
        raise ValueError(message)


def _choice(enum: type[Enum], value: object, setting: str) -> Enum:
    """``value`` as a member of ``enum``; a ValueError naming ``setting`` and the allowed values otherwise."""
    try:
        return enum(value.value if isinstance(value, Enum) else value)
    except ValueError:
        raise ValueError(f"{setting}={value!r}; expected one of {[m.value for m in enum]}") from None


@dataclass
class SelectionConfig:
    """Forward-backward consistency and correspondence selection (``tracker.correspondence``).

    Attributes:
        method: see :class:`SelectionMethod`.
        num_correspondences: correspondences kept per frame pair.
        grid: regions (rows, cols) of ``local_best_k``.
        max_inconsistency: forward-backward inconsistency (pixels) a correspondence may have.
        min_valid_fraction: selection fails (constant motion) below this fraction of consistent pixels.
        min_region_fraction: ``local_best_k`` regions with fewer consistent pixels are skipped.
        crop_top: fraction of image rows at the top not used.
    """

    method: SelectionMethod = SelectionMethod.local_best_k
    num_correspondences: int = 2000
    grid: list[int] = field(default_factory=lambda: [10, 10])
    max_inconsistency: float = 0.1
    min_valid_fraction: float = 0.1
    min_region_fraction: float = 0.1
    crop_top: float = 0.0

    def __post_init__(self) -> None:
        self.method = _choice(SelectionMethod, self.method, "tracker.correspondence.method")
        _check(len(self.grid) == 2 and all(int(g) > 0 for g in self.grid),
               f"tracker.correspondence.grid={list(self.grid)}; expected [rows, cols] of positive integers")
        self.grid = [int(g) for g in self.grid]
        _check(int(self.num_correspondences) > 0, f"tracker.correspondence.num_correspondences="
                                                 f"{self.num_correspondences}; expected a positive integer")
        _check(self.max_inconsistency > 0, f"tracker.correspondence.max_inconsistency={self.max_inconsistency}; "
                                           "expected > 0")
        _check(0.0 <= self.crop_top < 1.0, f"tracker.correspondence.crop_top={self.crop_top}; expected [0, 1)")


@dataclass
class EssentialConfig:
    """Essential-matrix RANSAC and its validity rules (``tracker.essential``).

    Attributes:
        threshold_px: RANSAC inlier threshold in pixels (converted to normalised coordinates).
        iterations: minimal samples per RANSAC repeat; repeats: repeats, the most inliers wins.
        min_correspondences: with this many or fewer valid correspondences E is invalid.
        min_cheirality_fraction: E is invalid when fewer rows pass cheirality.
    """

    threshold_px: float = 0.2
    iterations: int = 20
    repeats: int = 5
    min_correspondences: int = 10
    min_cheirality_fraction: float = 0.1

    def __post_init__(self) -> None:
        _check(self.threshold_px > 0, f"tracker.essential.threshold_px={self.threshold_px}; expected > 0")
        _check(int(self.iterations) > 0 and int(self.repeats) > 0,
               f"tracker.essential: iterations={self.iterations}, repeats={self.repeats}; expected positive integers")


@dataclass
class ModelSelectionConfig:
    """E-tracker or PnP-tracker (``tracker.model_selection``).

    Attributes:
        method: see :class:`ModelSelectionMethod`.
        h_threshold_px, h_iterations: homography RANSAC for GRIC.
        gric_sigma: fixed residual standard deviation of GRIC (pixels).
        flow_magnitude_threshold: ``flow``: PnP when the median flow is at most this many pixels.
    """

    method: ModelSelectionMethod = ModelSelectionMethod.gric
    h_threshold_px: float = 1.0
    h_iterations: int = 50
    gric_sigma: float = 0.8
    flow_magnitude_threshold: float = 5.0

    def __post_init__(self) -> None:
        self.method = _choice(ModelSelectionMethod, self.method, "tracker.model_selection.method")
        _check(self.h_threshold_px > 0 and self.gric_sigma > 0 and int(self.h_iterations) > 0,
               f"tracker.model_selection: h_threshold_px={self.h_threshold_px}, gric_sigma={self.gric_sigma}, "
               f"h_iterations={self.h_iterations}; expected positive values")


@dataclass
class ScaleConfig:
    """Scale of the E-tracker's unit translation from CNN depth (``tracker.scale``).

    Attributes:
        method: see :class:`ScaleMethod`.
        depth_views: 2 (default, our addition): the scale from the earlier frame's CNN depth and, separately, from
            the later frame's, combined by their geometric mean (one alone when the other fails); per-frame errors
            of the CNN depth's scale are nearly independent between frames, so two views halve their variance.
            1: the paper (earlier frame only).
        views_max_ratio: two views further apart than this factor are not averaged (the earlier frame's is used).
        min_points, ransac_trials, ransac_samples, inlier_threshold: the 1-D RANSAC on depth ratios.
        iterative_max_iters, iterative_tol, iterative_flow_threshold_px: Algorithm 2.
        max_depth, depth_crop_top: depth used for scale (and PnP) lies in (0, max_depth] metres and below the top
            ``depth_crop_top`` fraction of the rows.
    """

    method: ScaleMethod = ScaleMethod.simple
    depth_views: int = 2
    views_max_ratio: float = 1.5
    min_points: int = 10
    ransac_trials: int = 100
    ransac_samples: int = 3
    inlier_threshold: float = 0.1
    iterative_max_iters: int = 5
    iterative_tol: float = 1e-3
    iterative_flow_threshold_px: float = 5.0
    max_depth: float = 50.0
    depth_crop_top: float = 0.3

    def __post_init__(self) -> None:
        self.method = _choice(ScaleMethod, self.method, "tracker.scale.method")
        _check(self.depth_views in (1, 2), f"tracker.scale.depth_views={self.depth_views}; expected 1 or 2")
        _check(self.views_max_ratio > 1.0, f"tracker.scale.views_max_ratio={self.views_max_ratio}; expected > 1")
        _check(self.max_depth > 0 and self.inlier_threshold > 0,
               f"tracker.scale: max_depth={self.max_depth}, inlier_threshold={self.inlier_threshold}; expected > 0")
        _check(0.0 <= self.depth_crop_top < 1.0, f"tracker.scale.depth_crop_top={self.depth_crop_top}; "
                                                 "expected [0, 1)")
        for name in ("ransac_trials", "ransac_samples", "iterative_max_iters"):
            _check(int(getattr(self, name)) > 0, f"tracker.scale.{name}={getattr(self, name)}; expected a positive "
                                                 "integer")


@dataclass
class PnPConfig:
    """PnP-RANSAC with Levenberg-Marquardt refinement (``tracker.pnp``).

    Attributes:
        threshold_px: inlier reprojection threshold (pixels). iterations: minimal samples per repeat.
        repeats: RANSAC repeats. min_points: PnP fails with fewer usable 3-D/2-D rows.
    """

    threshold_px: float = 1.0
    iterations: int = 100
    repeats: int = 5
    min_points: int = 10

    def __post_init__(self) -> None:
        _check(self.threshold_px > 0 and int(self.iterations) > 0 and int(self.repeats) > 0,
               f"tracker.pnp: threshold_px={self.threshold_px}, iterations={self.iterations}, repeats={self.repeats}; "
               "expected positive values")


@dataclass
class TrackerConfig:
    """Every setting of the odometry loop (:class:`dfvo.tracking.VisualOdometry`).

    Attributes:
        mode: see :class:`TrackerMode`.
        seed: frame k of a sequence draws its random samples from ``torch.Generator().manual_seed(seed + k)``.
        correspondence, essential, model_selection, scale, pnp: the stages' sections.
    """

    mode: TrackerMode = TrackerMode.hybrid
    seed: int = 0
    correspondence: SelectionConfig = field(default_factory=SelectionConfig)
    essential: EssentialConfig = field(default_factory=EssentialConfig)
    model_selection: ModelSelectionConfig = field(default_factory=ModelSelectionConfig)
    scale: ScaleConfig = field(default_factory=ScaleConfig)
    pnp: PnPConfig = field(default_factory=PnPConfig)

    def __post_init__(self) -> None:
        self.mode = _choice(TrackerMode, self.mode, "tracker.mode")
