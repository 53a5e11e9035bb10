"""Tracker configuration: one typed node (``tracker`` in ``infer.py``'s config) with one section per stage.

This dataclass holds every tracker default once; the YAML files of the config groups ``tracker``,
``correspondence``, ``scale`` and ``model_selection`` (``dfvo/conf/infer/``) only select a choice (e.g.
``method: best_n``) and the command line overrides single values (``tracker.scale.depth_views=1``). The defaults are
what ``infer.py`` runs; where they differ from the paper / the authors' code, the field says so and
``experiment=paper`` restores the paper's configuration. Defaults read from the official implementation are in
``../shared/reference/official-defaults.md``.

Three sections live beside the function they configure, in a lower layer, so that function takes its defaults from
them (``select_correspondences`` cannot import the tracker): :class:`SelectionConfig` in
:mod:`dfvo.matching.selection`, :class:`EssentialConfig` in :mod:`dfvo.geometry.two_view`, :class:`PnPConfig` in
:mod:`dfvo.geometry.pnp`; they are re-exported here. ``tests/test_config_defaults.py`` checks that every public
function whose parameters mirror a config field has the field's default (or none).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum

from dfvo.geometry.pnp import PnPConfig
from dfvo.geometry.two_view import EssentialConfig
from dfvo.matching.selection import SelectionConfig, SelectionMethod
from dfvo.validation import check, choice

__all__ = ["TrackerMode", "SelectionMethod", "ModelSelectionMethod", "ScaleMethod", "RoadPoints", "SelectionConfig",
           "EssentialConfig", "ModelSelectionConfig", "ScaleConfig", "RoadPlaneConfig", "CameraHeightConfig",
           "RoadAlignmentConfig", "ScaleFilterConfig", "GateConfig", "PnPConfig", "CovarianceConfig", "WindowConfig",
           "MotionModel", "HandheldConfig", "MotionAutoConfig", "TrackerConfig"]


class TrackerMode(StrEnum):
    """Which trackers run: ``hybrid`` (E-tracker, PnP when E is unreliable; the paper), ``e`` (E only; constant
    motion when invalid), ``pnp`` (PnP only)."""

    hybrid = "hybrid"
    e = "e"
    pnp = "pnp"


class ModelSelectionMethod(StrEnum):
    """E-vs-PnP decision: ``gric`` (E vs H) or ``flow`` (median flow magnitude)."""

    gric = "gric"
    flow = "flow"


class PlanarMotion(StrEnum):
    """What tracks a pair whose correspondences a homography explains (GRIC prefers H; ``tracker.model_selection.
    planar``): ``pnp`` (the paper: the PnP-tracker on the CNN depth) or ``homography`` (the homography's own
    decomposition gives R and the translation's direction, scaled like an E-tracker's result; PnP when it fails)."""

    pnp = "pnp"
    homography = "homography"


class MotionModel(StrEnum):
    """How the camera moves (``tracker.motion``; :mod:`dfvo.tracking.motion_model`): ``car`` (a vehicle's inertia:
    the gate and model-selection settings as they are), ``handheld`` (a hand or a small robot turns its motion for
    good from one frame to the next and films planar scenes: :class:`HandheldConfig` replaces those settings) or
    ``auto`` (``car`` until the first frames' motion says which: :class:`MotionAutoConfig`)."""

    car = "car"
    handheld = "handheld"
    auto = "auto"


class RoadPoints(StrEnum):
    """The points the road plane is fitted to (``tracker.road_plane.points``; see :class:`RoadPlaneConfig`):
    ``none`` fits none for a scale observation (the photometric road scale, ``tracker.road_alignment``, still uses
    the network's plane to place its patch)."""

    triangulated = "triangulated"
    depth = "depth"
    none = "none"


class ScaleMethod(StrEnum):
    """Scale recovery: ``simple`` (1-D RANSAC on depth ratios) or ``iterative`` (paper Algorithm 2)."""

    simple = "simple"
    iterative = "iterative"


MAX_CAMERA_HEIGHT_M = 20.0  # a camera higher above the road than this is a unit mistake (165 cm given as 165)


def check_camera_height(height: float | None, setting: str) -> None:
    """A camera height in metres: None (unknown / off) or in (0, :data:`MAX_CAMERA_HEIGHT_M`]; else one line naming
    ``setting``, with the centimetre reading when the value looks like one."""
    if height is None:
        return
    check(float(height) > 0, f"{setting}={height}; expected a height in metres > 0, or null (off)")
    check(float(height) <= MAX_CAMERA_HEIGHT_M,
          f"{setting}={height}; expected metres (the camera's height above the road, at most {MAX_CAMERA_HEIGHT_M:g} "
          f"m); for {height} cm give {float(height) / 100:g}")


def check_direction_confirmation(frames: int | None, by_pnp_deg: float | None, section: str,
                                 length_frames: int | None = None) -> None:
    """The gates' confirmations of a new motion (``confirm_direction_frames``, ``confirm_direction_by_pnp_deg``,
    ``confirm_length_frames``) as a car's ``tracker.gate`` or a hand's ``tracker.handheld`` sets them: null (off), or
    at least 2 frames and an angle in (0, 180) degrees; one line naming ``section``'s field otherwise."""
    check(frames is None or int(frames) >= 2,
          f"{section}.confirm_direction_frames={frames}; expected null (off) or >= 2")
    check(length_frames is None or int(length_frames) >= 2,
          f"{section}.confirm_length_frames={length_frames}; expected null (off) or >= 2")
    check(by_pnp_deg is None or 0.0 < float(by_pnp_deg) < 180.0,
          f"{section}.confirm_direction_by_pnp_deg={by_pnp_deg}; expected null (off) or an angle in (0, 180) degrees")


@dataclass
class ModelSelectionConfig:
    """E-tracker or PnP-tracker (``tracker.model_selection``).

    Attributes:
        method: see :class:`ModelSelectionMethod`.
        h_threshold_px, h_iterations: homography RANSAC for GRIC.
        gric_sigma: fixed residual standard deviation of GRIC (pixels).
        flow_magnitude_threshold: ``flow``: PnP when the median flow is at most this many pixels.
        min_parallax_px: E is kept, whatever ``method`` prefers, when its inliers' median image motion beyond the
            camera's rotation is at least this many pixels (the translation is visible, so its direction is
            measurable: a turning car at any speed), and (with ``gric``) the homography's median residual on E's
            inliers is at least ``min_homography_residual_ratio`` times E's own, taken as at least
            ``residual_floor_px`` (the selected flow's noise) (not one plane: on a planar scene E's decomposition is
            ambiguous and GRIC's choice stands). null: the paper (the method alone decides).
            Measured in docs/scale.md (KITTI 07's turns).
        planar: see :class:`PlanarMotion`. With ``homography``, of the decompositions that put most of the plane's
            inliers in front of the camera (:func:`dfvo.geometry.homography.decompose_homography`) the one whose
            plane best explains the shape of the CNN depth there (its inverse depth up to scale; without depth, the
            one nearest the previous homography frame's plane) gives R and the direction, when its translation shows
            at least ``min_parallax_px`` beyond the rotation; its scale is the E-tracker's (CNN depth, the filter,
            the gates). Needs ``method=gric``.
    """

    method: ModelSelectionMethod = ModelSelectionMethod.gric
    h_threshold_px: float = 1.0
    h_iterations: int = 50
    gric_sigma: float = 0.8
    flow_magnitude_threshold: float = 5.0
    min_parallax_px: float | None = 1.0
    min_homography_residual_ratio: float = 2.0
    residual_floor_px: float = 0.05
    planar: PlanarMotion = PlanarMotion.pnp

    def __post_init__(self) -> None:
        self.method = choice(ModelSelectionMethod, self.method, "tracker.model_selection.method")
        self.planar = choice(PlanarMotion, self.planar, "tracker.model_selection.planar")
        check(self.planar == PlanarMotion.pnp or self.method == ModelSelectionMethod.gric,
              f"tracker.model_selection.planar={self.planar.value} needs method=gric (the homography GRIC fits)")
        check(self.h_threshold_px > 0 and self.gric_sigma > 0 and int(self.h_iterations) > 0,
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
        camera_height: the camera's height above the road in metres (KITTI: 1.65); a road plane fit
            (:mod:`dfvo.tracking.ground_plane`, settings in ``tracker.road_plane``) then gives a second scale
            observation, fused with the CNN's by their variances (:mod:`dfvo.tracking.scale_fusion`). null: off (the
            paper). ``infer.py`` fills it from ``data.camera_height`` when null (KITTI's dataset configs set 1.65;
            ``data.camera_height=null`` turns it off there). Its effect is measured in docs/scale.md.
        camera_height_from_data: false: ``data.camera_height`` is not used (``experiment=paper`` sets it; an explicit
            ``camera_height`` still is).
        temporal: fuse the scale over time (:mod:`dfvo.tracking.scale_filter`, settings in ``tracker.scale_filter``):
            the three-frame relative scale predicts each pair's length from the previous one, the absolute
            observations correct it; a frame whose scale observations fail keeps the prediction. false: per-frame
            scale (the paper). Default true; its effect is measured in docs/scale.md.
        fuse_pnp: a PnP frame's length (the depth network's scale) is one more observation of the scale fusion
            (its bias estimate, the three-frame relative scale, the road) instead of the frame's length as it is.
            Default false (PnP's own length, the paper's): on the accuracy panel it changes nothing on KITTI and is
            worse on the synthetic worlds' PnP frames with the default flow network (docs/scale.md).
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
    camera_height: float | None = None
    camera_height_from_data: bool = True
    temporal: bool = True
    fuse_pnp: bool = False

    def __post_init__(self) -> None:
        self.method = choice(ScaleMethod, self.method, "tracker.scale.method")
        check_camera_height(self.camera_height, "tracker.scale.camera_height")
        check(self.depth_views in (1, 2), f"tracker.scale.depth_views={self.depth_views}; expected 1 or 2")
        check(self.views_max_ratio > 1.0, f"tracker.scale.views_max_ratio={self.views_max_ratio}; expected > 1")
        check(self.max_depth > 0 and self.inlier_threshold > 0,
               f"tracker.scale: max_depth={self.max_depth}, inlier_threshold={self.inlier_threshold}; expected > 0")
        check(0.0 <= self.depth_crop_top < 1.0, f"tracker.scale.depth_crop_top={self.depth_crop_top}; "
                                                 "expected [0, 1)")
        for name in ("ransac_trials", "ransac_samples", "iterative_max_iters"):
            check(int(getattr(self, name)) > 0, f"tracker.scale.{name}={getattr(self, name)}; expected a positive "
                                                 "integer")


@dataclass
class RoadPlaneConfig:
    """The road plane of the camera-height scale (``tracker.road_plane``; used when a camera height is given or
    estimated): the depth network's plane always places the photometric road patch and gives the camera-height
    estimate (:mod:`dfvo.tracking.road_scale`, :mod:`dfvo.tracking.camera_height`); ``points`` chooses whether a plane
    fit is also a scale observation of its own.

    Attributes:
        points: ``none`` (default): no plane-fit observation; the photometric road scale (``tracker.road_alignment``)
            observes the length and the CNN-depth scale's bias is learnt against it. ``depth``: the plane of the
            depth network's own points of the earlier frame (a pixel grid every ``grid_step`` px in the band);
            ``fitted height / camera_height`` observes the network's scale factor near the road, which the filter
            divides out of the CNN-depth scale (the default before the photometric road scale: the network's bias
            near the road is not its bias at the correspondences, 3 % vs 7 % on KITTI 07). ``triangulated``: the plane
            among the E-tracker's selected inliers triangulated with its unit pose; ``camera_height / fitted height``
            observes the translation's length (needs good flow on the road, which the shipped flow is not).
            Measurements: docs/scale.md.
        min_row_fraction, max_row_fraction: candidate points lie in this band of image rows (fractions of the height;
            the lower image, above the bottom rows whose points leave the next image).
        max_col_offset_fraction: ... and within this fraction of the image width of its centre column.
        threshold: largest inlier distance to the plane as a fraction of the camera's height above it (the inlier
            distance adapts to the points' spread below it).
        quantile: the plane whose distances at this quantile of the candidates are least wins (at most the share
            of candidates expected on the road).
        max_tilt_deg: largest angle between the plane's normal and the camera's vertical (y) axis.
        min_parallax_deg: points whose two rays meet at a smaller angle are not used (poor triangulation).
        min_inliers: fewer inliers: no camera-height observation this frame.
        trials: RANSAC hypotheses. log_std: per-frame std of the observation's log, the weight the filter gives it
            (the values measured per dataset: docs/scale.md).
    """

    points: RoadPoints = RoadPoints.none
    min_row_fraction: float = 0.7
    max_row_fraction: float = 0.87
    max_col_offset_fraction: float = 0.2
    grid_step: int = 4
    threshold: float = 0.08
    quantile: float = 0.3
    max_tilt_deg: float = 15.0
    min_parallax_deg: float = 1.0
    min_inliers: int = 20
    trials: int = 100
    log_std: float = 0.05

    def __post_init__(self) -> None:
        self.points = choice(RoadPoints, self.points, "tracker.road_plane.points")
        check(self.min_row_fraction < self.max_row_fraction <= 1.0 and int(self.grid_step) > 0,
               f"tracker.road_plane: max_row_fraction={self.max_row_fraction}, grid_step={self.grid_step}; expected "
               "min_row_fraction < max_row_fraction <= 1 and a positive step")
        check(0.0 <= self.min_row_fraction < 1.0 and 0.0 < self.max_col_offset_fraction <= 0.5,
               f"tracker.road_plane: min_row_fraction={self.min_row_fraction} (expected [0, 1)), "
               f"max_col_offset_fraction={self.max_col_offset_fraction} (expected (0, 0.5])")
        check(0.0 < self.quantile <= 1.0, f"tracker.road_plane.quantile={self.quantile}; expected (0, 1]")
        check(self.threshold > 0 and 0 < self.max_tilt_deg < 90 and self.log_std > 0 and int(self.trials) > 0,
               f"tracker.road_plane: threshold={self.threshold}, max_tilt_deg={self.max_tilt_deg}, "
               f"log_std={self.log_std}, trials={self.trials}; expected positive values (tilt < 90)")


@dataclass
class CameraHeightConfig:
    """The camera's height when no dataset or setting gives it (``tracker.camera_height``,
    :mod:`dfvo.tracking.camera_height`).

    Attributes:
        estimate: estimate it from the depth network's road plane over the frames seen so far (false: without a
            given height there are no road observations).
        min_frames: frames with a road plane before the estimate is used.
        max_spread: the per-frame heights' robust relative spread above which the estimate is unusable (no steady
            road in view: indoors, hand-held).
        height_range: a plausible camera height above a road (metres); an estimate outside is unusable.
    """

    estimate: bool = True
    min_frames: int = 3
    max_spread: float = 0.15
    height_range: list[float] = field(default_factory=lambda: [0.3, 4.0])

    def __post_init__(self) -> None:
        self.height_range = [float(v) for v in self.height_range]
        check(len(self.height_range) == 2 and 0 < self.height_range[0] < self.height_range[1],
               f"tracker.camera_height.height_range={self.height_range}; expected [lo, hi] metres with 0 < lo < hi")
        check(int(self.min_frames) >= 1 and self.max_spread > 0,
               f"tracker.camera_height: min_frames={self.min_frames} (expected >= 1), max_spread={self.max_spread} "
               "(expected > 0)")


@dataclass
class RoadAlignmentConfig:
    """The photometric road scale (``tracker.road_alignment``, :mod:`dfvo.tracking.road_scale`): the road ahead aligned
    between the two images by the homography of its plane gives the camera's height in the unit of the E-tracker's
    translation, so the camera height in metres over it is the translation's length. Used when a camera height is
    known or estimated (``tracker.scale.camera_height``, ``tracker.camera_height``).

    Attributes:
        enabled: false: not used (the paper has no road scale).
        min_depth, max_depth: the patch covers the road this far ahead of the camera (metres, placed with the depth
            network's road plane), moved further by ``motion_margin`` times the expected travel (fast motion: the
            near road leaves the later image). half_width: ... and this far either side of the line of sight.
        normal_from_motion: the road normal is the network's, with its component along the E-tracker's translation
            removed (a car moves along its road): the network's plane pitch is often off by ~0.5 deg, which moves the
            road's distance by ~5 % at 10 m; the translation's direction fixes the pitch. false: the network's normal.
        min_pixels: a smaller patch (a low-resolution image, or a camera that sees no road there) gives nothing. On
            the synthetic drive with exact depth the road scale errs by 1-2 % at 192x640 (a 6,000-12,000 px patch) and
            by 3-13 % at 96x320 (1,400-2,900 px).
        span, steps: with a prediction the search covers the expected unit height times/divided by ``span`` in
            ``2 steps - 1`` log-spaced samples; without one, or when nothing is found there, the whole
            ``wide_range`` (camera height over translation length: 0.3..100 covers 1.65 m at 0.017-5.5 m a frame) in
            steps of ``coarse_step`` in log height (on every 2nd pixel), then ``steps`` samples over +-2 coarse
            steps around its best (every pixel). The best three samples are refined by a parabola.
        block_max_cost: a block (near/far x left/centre/right) whose best 1 - ZNCC exceeds this is left out
            (a car, a shadow edge); min_blocks: fewer blocks left: nothing. max_cost: the mean profile's best cost
            must be at most this.
        log_std: standard deviation of the observation's log (the filter's measurement noise).
        max_height_ratio: the network's road height places the patch unless it differs from the camera's height
            (given or estimated) by more than this factor either way; then the camera height does (a network 3x too
            far put the patch 18-45 m ahead, where no frame aligned: ``tests/tracking/test_road_scale.py``). Always
            the camera height was measured too: KITTI 06 -8 %, 07 +8 % RPE with the shipped network (docs/scale.md).
    """

    enabled: bool = True
    min_depth: float = 6.0
    max_depth: float = 15.0
    motion_margin: float = 1.0
    half_width: float = 2.5
    normal_from_motion: bool = True
    min_pixels: int = 3000
    span: float = 2.0
    steps: int = 21
    coarse_step: float = 0.05
    wide_range: list[float] = field(default_factory=lambda: [0.3, 100.0])
    block_max_cost: float = 0.05
    min_blocks: int = 2
    max_cost: float = 0.05
    log_std: float = 0.07
    max_height_ratio: float = 1.5

    def __post_init__(self) -> None:
        check(self.max_height_ratio > 1.0, f"tracker.road_alignment.max_height_ratio={self.max_height_ratio}; "
                                           "expected > 1")
        check(0 < self.min_depth < self.max_depth and self.half_width > 0,
               f"tracker.road_alignment: min_depth={self.min_depth}, max_depth={self.max_depth}, half_width="
               f"{self.half_width}; expected 0 < min_depth < max_depth and half_width > 0")
        check(self.span > 1 and self.coarse_step > 0 and int(self.steps) >= 5 and self.log_std > 0,
               f"tracker.road_alignment: span={self.span} (expected > 1), coarse_step={self.coarse_step} (expected > "
               f"0), steps={self.steps} (expected >= 5), log_std={self.log_std} (expected > 0)")
        self.wide_range = [float(v) for v in self.wide_range]
        check(len(self.wide_range) == 2 and 0 < self.wide_range[0] < self.wide_range[1],
               f"tracker.road_alignment.wide_range={list(self.wide_range)}; expected [lo, hi] with 0 < lo < hi")
        check(1 <= int(self.min_blocks) <= 6, f"tracker.road_alignment.min_blocks={self.min_blocks}; expected 1..6")


@dataclass
class ScaleFilterConfig:
    """Scale fusion and the temporal filter over log scale (``tracker.scale_filter``).

    Attributes:
        cnn_log_std: per-frame std of log(CNN-depth scale / true length), the weight the filter gives the CNN-depth
            scale. Its errors are correlated from frame to frame, so the default is larger than the per-frame std
            measured on KITTI and lets the three-frame relative scale carry more (measurements: docs/scale.md).
        motion_log_std: per-frame random walk of log scale when no relative scale is observed.
        temporal_log_std: floor of the three-frame relative scale's standard error; relative_process_std: added
            per frame to it (speed changes the points cannot see).
        bias_prior_log_std, bias_log_std: prior std of the depth network's log scale bias and its per-frame random
            walk (estimated only with ``camera_height`` and ``temporal``).
        gate_sigma: absolute observations further than this many standard deviations from the prediction are
            rejected (once the filter has converged). When the absolute observations together disagree with the
            prediction beyond it, and with each other within it, the frame counts towards ``max_rejections`` (a
            prediction that ran away, e.g. a relative scale wrong over several frames of a turn, cannot outvote
            them for long; two observations that contradict each other are no evidence against it).
        max_inconsistency: forward-backward inconsistency (px) allowed at the previous pair's points.
        min_parallax_deg: both triangulations of a shared point need this parallax.
        min_points: fewer shared points: no relative scale this frame.
        min_length: a frame that moved less (m) makes the filter forget the scale and gives no relative scale to the
            next (a stop, or a rotation in place).
        max_rejections: frames in a row whose absolute observations were all gated out before the filter restarts.
        warmup_frames: no observation is gated out before this many frames have been fused since the scale was
            last unknown (the start of a sequence, after a stop): the first observation only starts the average.
        temporal_rotation_log_std: added (per degree of the pair's rotation) to the three-frame relative scale's
            standard error: it re-triangulates the previous pair's points with this pair's pose, and its error grows in
            turns, which the points' own spread does not show.
        refine_points: carry the previous pair's points into the next image by a pyramidal Lucas–Kanade at the points
            themselves (forward and backward, its own consistency) instead of the dense flow: for
            ``flow.refine.mode=pyramid``, whose dense flow away from its candidates is the network's raw flow.
    """

    cnn_log_std: float = 0.1
    motion_log_std: float = 0.1
    temporal_log_std: float = 0.005
    relative_process_std: float = 0.005
    bias_prior_log_std: float = 0.5
    bias_log_std: float = 0.005
    gate_sigma: float = 3.0
    max_inconsistency: float = 0.5
    min_parallax_deg: float = 0.5
    min_points: int = 20
    min_length: float = 0.1
    max_rejections: int = 3
    warmup_frames: int = 5
    temporal_rotation_log_std: float = 0.005
    refine_points: bool = False

    def __post_init__(self) -> None:
        for name in ("cnn_log_std", "motion_log_std", "temporal_log_std", "gate_sigma", "max_inconsistency"):
            check(getattr(self, name) > 0, f"tracker.scale_filter.{name}={getattr(self, name)}; expected > 0")
        for name in ("relative_process_std", "bias_prior_log_std", "bias_log_std", "min_parallax_deg"):
            check(getattr(self, name) >= 0, f"tracker.scale_filter.{name}={getattr(self, name)}; expected >= 0")


@dataclass
class GateConfig:
    """Plausibility gates of the trackers' results (``tracker.gate``, :mod:`dfvo.tracking.gates`).

    Attributes:
        enabled: false: every result is used (the paper).
        max_length_ratio: a translation more than this factor longer (or shorter) than the expected one is rejected.
        warmup_length_ratio: the factor while the expectation rests on fewer than ``length_window`` lengths (a
            sequence's first frames, whose scale may be far off: at highway speed the first frame's CNN scale can be
            half the truth, and the right lengths after it must not be rejected).
        min_reference_length: the expected length is taken as at least this (m) when judging "too long" (starts from
            standstill). stop_length, stop_flow_px: a translation this short is a stop, never "too short", when the
            image agrees (90 % of the selected correspondences move at most ``stop_flow_px`` pixels beyond the
            camera's rotation: no parallax).
        length_window: the expected length is the median of this many last tracked lengths (not constant motion);
            more than one keeps a single wrong PnP length from becoming the reference (docs/scale.md).
        max_direction_change_deg: a translation whose direction differs more from the previous frame's (both longer
            than ``stop_length``) is rejected.
        min_inliers, min_inlier_fraction: a model with fewer inliers than ``max(min_inliers,
            min_inlier_fraction * rows)`` is rejected.
        max_consecutive: after this many frames in a row that a gate sent to constant motion the next result is
            accepted (a wrong expectation cannot hold forever); the default, 1 s at 10 Hz, rides out a truck that
            fills the view for longer than a few frames (docs/scale.md).
        adaptive_sigmas: the length ratio and the direction change allowed widen to this many robust standard
            deviations of the sequence's own frame-to-frame changes (of the log length between consecutive tracked
            steps, and of their direction) when those are wider than the fixed limits above: a hand or a small robot
            speeds up, stops and turns from one frame to the next, a car does not (its changes stay far inside the
            fixed limits, which then apply unchanged). 0: the fixed limits alone.
        adaptive_window, adaptive_min_changes: the changes are those of the last ``adaptive_window`` frames, used
            once at least ``adaptive_min_changes`` of them are known.
        confirm_direction_frames: a direction the direction gate rejects is accepted once this many frames in a row
            agree on it (each within ``max_direction_change_deg`` of the others; the earlier ones fell back to
            constant motion): a hand turns for good from one frame to the next, where the gate would hold the old
            direction for ``max_consecutive`` frames. null (the default): off; a car's E-tracker locked onto a truck
            filling the view also agrees with itself for several frames.
        confirm_direction_by_pnp_deg: when the direction gate rejects the two-view result (E or the homography)
            and PnP's result of the same frame, rejected too (by its turn or its length), points within this angle
            (degrees) of it, the two-view result is accepted: two trackers that share the flow but not the geometry
            (the epipolar constraint alone; the depth network's points) find the same new direction, so the motion
            turned. null (the default): off; a car's trackers locked onto a truck filling the view agree too. Needs
            ``tracker.mode=hybrid`` (the default; PnP does not run otherwise).
        confirm_length_frames: a length the length gate rejects is accepted once this many frames in a row each had
            a result rejected by it and their lengths agree (each pair within the gate's own ratio, ``max_length_ratio``
            or the sequence's wider one); the expectation then restarts from those lengths: a hand slows down (or
            speeds up) threefold from one frame to the next and stays at its new pace, where the gate would hold the
            old length for ``max_consecutive`` frames. The scale filter keeps its own restart
            (``scale_filter.max_rejections``: restarting it as early made ``handheld_markers`` worse, docs/robots.md).
            null (the default): off; a car's trackers locked onto a truck filling the view agree with themselves too.
    """

    enabled: bool = True
    max_length_ratio: float = 2.0
    warmup_length_ratio: float = 4.0
    min_reference_length: float = 0.7
    stop_length: float = 0.1
    stop_flow_px: float = 1.0
    length_window: int = 3
    max_direction_change_deg: float = 45.0
    min_inliers: int = 15
    min_inlier_fraction: float = 0.2
    max_consecutive: int = 10
    adaptive_sigmas: float = 3.0
    adaptive_window: int = 30
    adaptive_min_changes: int = 8
    confirm_direction_frames: int | None = None
    confirm_direction_by_pnp_deg: float | None = None
    confirm_length_frames: int | None = None

    def __post_init__(self) -> None:
        check(self.adaptive_sigmas >= 0 and int(self.adaptive_window) >= 2 and int(self.adaptive_min_changes) >= 1,
              f"tracker.gate: adaptive_sigmas={self.adaptive_sigmas} (expected >= 0), adaptive_window="
              f"{self.adaptive_window} (expected >= 2), adaptive_min_changes={self.adaptive_min_changes} (expected "
              ">= 1)")
        check(self.max_length_ratio > 1.0, f"tracker.gate.max_length_ratio={self.max_length_ratio}; expected > 1")
        check(int(self.length_window) >= 1 and int(self.max_consecutive) >= 0,
               f"tracker.gate: length_window={self.length_window} (expected >= 1), max_consecutive="
               f"{self.max_consecutive} (expected >= 0)")
        check_direction_confirmation(self.confirm_direction_frames, self.confirm_direction_by_pnp_deg, "tracker.gate",
                                     self.confirm_length_frames)
        check(0.0 <= self.min_inlier_fraction < 1.0, f"tracker.gate.min_inlier_fraction="
                                                      f"{self.min_inlier_fraction}; expected [0, 1)")


@dataclass
class HandheldConfig:
    """What a hand-held camera's motion changes (``tracker.handheld``): these values replace the fields of the same
    name of ``tracker.gate`` and ``tracker.model_selection`` (a car's) whenever the motion is hand-held
    (``tracker.motion=handheld``, or ``auto`` judged so).

    Attributes:
        confirm_direction_frames: :attr:`GateConfig.confirm_direction_frames` for a hand (null: off).
        confirm_direction_by_pnp_deg: :attr:`GateConfig.confirm_direction_by_pnp_deg` for a hand (null: off).
        confirm_length_frames: :attr:`GateConfig.confirm_length_frames` for a hand (null: off).
        planar: :attr:`ModelSelectionConfig.planar` for a hand (the homography's own decomposition on a desk or a
            wall, where PnP would trust the driving-trained depth); with ``model_selection.method=flow`` (no
            homography is fitted) PnP tracks planar pairs whatever this says (``summary.json``'s ``motion.settings``
            gives what ran).
    With ``auto`` or ``handheld`` a value set in ``tracker.gate`` / ``tracker.model_selection`` for these four
    fields is a car's: after a hand-held verdict this section's apply (set ``tracker.motion=car`` to keep them).
    Measured in docs/robots.md (the synthetic hand-held world and ``handheld_markers``).
    """

    confirm_direction_frames: int | None = 2
    confirm_direction_by_pnp_deg: float | None = 45.0
    confirm_length_frames: int | None = 2
    planar: PlanarMotion = PlanarMotion.homography

    def __post_init__(self) -> None:
        self.planar = choice(PlanarMotion, self.planar, "tracker.handheld.planar")
        check_direction_confirmation(self.confirm_direction_frames, self.confirm_direction_by_pnp_deg,
                                     "tracker.handheld", self.confirm_length_frames)


@dataclass
class MotionAutoConfig:
    """How ``tracker.motion=auto`` judges the motion (``tracker.motion_auto``, :class:`dfvo.tracking.motion_model.
    MotionJudge`): a car moves along its optical axis, a hand in every direction.

    Attributes:
        frames: the judgement is made once this many frames have measured their translation's direction (the
            two-view or PnP result, accepted by the gates or not), with at least ``min_parallax_px`` of image
            motion beyond the camera's rotation (a stop or a pure turn shows no direction).
        off_axis_deg: hand-held when the median angle between those translations and the optical axis (either
            way: a car may reverse) exceeds this. Measured on ground truth (docs/robots.md): the first 10 steps'
            median is 0.2-8.7 deg on every road (KITTI 06, 07, raw 0005, the synthetic worlds; at most 13 deg on
            one step), 33-70 deg on the hand-held cases.
        min_parallax_px: see ``frames``. Below ~0.3 px the measured directions are noise (up to 75 deg off on a
            synthetic highway whose flow fails); a hand-held camera often moves less than 1 px a frame
            (``handheld_markers``: judged at frame 13 with 0.5, 28 with 1.0).
        revise_frames: after a car's verdict, the last this many measured translations (counted as for ``frames``)
            are judged again on every frame that counts one: when their median angle to the optical axis exceeds
            ``off_axis_deg`` and their median angle above or below the camera's horizontal plane (x-z) exceeds
            ``revise_elevation_deg``, the motion turns hand-held for the rest of the sequence (a hand whose first
            moves ran along the optical axis, or were measured so). A car moves in that plane whatever it does
            (the synthetic drive's sideways steps, 73-86 deg off the axis, lie in it). A hand-held verdict is
            final. None: the first verdict is final.
        revise_elevation_deg: see ``revise_frames``. Measured (docs/robots.md): the 10-frame medians stay at or
            below 2.2 deg on every road (KITTI 06, 07, raw 0005, the synthetic worlds); a hand held over a desk
            moves 20-60 deg out of it.
    """

    frames: int = 5
    off_axis_deg: float = 25.0
    min_parallax_px: float = 0.5
    revise_frames: int | None = 10
    revise_elevation_deg: float = 10.0

    def __post_init__(self) -> None:
        check(int(self.frames) >= 1 and 0.0 < float(self.off_axis_deg) < 90.0 and float(self.min_parallax_px) >= 0
              and (self.revise_frames is None or int(self.revise_frames) >= 1)
              and 0.0 <= float(self.revise_elevation_deg) < 90.0,
              f"tracker.motion_auto: frames={self.frames} (expected >= 1), off_axis_deg={self.off_axis_deg} (expected "
              f"(0, 90)), min_parallax_px={self.min_parallax_px} (expected >= 0), revise_frames="
              f"{self.revise_frames} (expected null or >= 1), revise_elevation_deg={self.revise_elevation_deg} "
              "(expected [0, 90))")


@dataclass
class CovarianceConfig:
    """Per-frame covariance of the relative step (``tracker.covariance``; :mod:`dfvo.tracking.covariance`).

    Attributes:
        inflation: factor on the part of the E and PnP covariances that comes from the normal equations (pixel
            noise; not the length's variance from the scale filter). 1: the normal equations as they are, consistent
            on the synthetic world with independent pixel noise (``tests/tracking/test_covariance.py``). Real flow
            errors are correlated between neighbouring pixels, which shrinks the effective number of
            correspondences: the default 160 is calibrated on KITTI 07 with the shipped networks (rotation NEES
            3.0 there; with the blocks alone, mean 6-DoF NEES 6.8 on KITTI 06 and 5.4 on 07, ``docs/robots.md``).
            Use 1 with exact flow plus independent noise (the synthetic world's oracle).
        constant_motion_rot_std: rotation std (rad, per axis) of a constant-motion frame (the previous motion
            repeated): 0.1 rad = 5.7 degrees.
        constant_motion_trans_std: translation std (m, per axis) of a constant-motion frame, or the step's length
            when that is larger.
        correlated: keep the normal equations' correlation between the rotation and the translation errors. It
            holds for independent pixel noise (the synthetic test's model: use it with ``inflation=1``); measured on
            real flow it does not: the rotation-translation blocks alone (false, the default) take the mean 6-DoF
            NEES from 18.8 / 13.3 / 111 to 6.8 / 5.4 / 36.7 on KITTI 06 / 07 / raw 0005 with the same inflation,
            poses unchanged (``docs/robots.md``).
    """

    inflation: float = 160.0
    constant_motion_rot_std: float = 0.1
    constant_motion_trans_std: float = 1.0
    correlated: bool = False

    def __post_init__(self) -> None:
        check(self.inflation > 0 and self.constant_motion_rot_std > 0 and self.constant_motion_trans_std > 0,
              f"tracker.covariance: inflation={self.inflation}, constant_motion_rot_std="
              f"{self.constant_motion_rot_std}, constant_motion_trans_std={self.constant_motion_trans_std}; "
              "expected positive values")


@dataclass
class WindowConfig:
    """Sliding-window bundle adjustment of each latest step (``tracker.window``; :mod:`dfvo.tracking.window_refinement`;
    beyond the paper, off by default).

    Attributes:
        enabled: refine each step over the window (the tracker's own decisions are unchanged).
        frames: frames in the window (>= 3): the latest ``frames - 1`` steps and the tracks through them.
        iterations: Levenberg–Marquardt iterations per frame.
        pixel_sigma: standard deviation (pixels) of a track's position; the weight is also divided by
            ``tracker.covariance.inflation`` (correlated flow errors, as in the steps' covariances).
        robust_px: scale (pixels) of the Cauchy loss on the reprojection residuals.
        max_inconsistency: forward-backward inconsistency (pixels) up to which a track is carried into the next frame.
        cell_px: a pair's correspondences start new tracks only in cells of this size (pixels) that hold no carried
            track, one per cell (bounds the problem's size; spreads the tracks over the image).
        depth_log_std: standard deviation of a track's log depth around the depth network's (times the window's
            triangulated-over-CNN ratio).
        min_parallax_deg: triangulation angle below which a track's first depth is the network's.
        min_tracks: fewer tracks: the step is not refined.
        max_rotation_change_deg, max_length_change: a refinement that turns the step by more (degrees) or changes
            its length by more (relative) is not used (flagged ``window_rejected``).
    """

    enabled: bool = False
    frames: int = 4
    iterations: int = 5
    pixel_sigma: float = 1.0
    robust_px: float = 1.0
    max_inconsistency: float = 0.5
    cell_px: int = 8
    depth_log_std: float = 0.3
    min_parallax_deg: float = 0.5
    min_tracks: int = 50
    max_rotation_change_deg: float = 0.5
    max_length_change: float = 0.25

    def __post_init__(self) -> None:
        check(int(self.frames) >= 3 and int(self.iterations) >= 1 and int(self.min_tracks) >= 1
              and int(self.cell_px) >= 1,
              f"tracker.window: frames={self.frames} (expected >= 3), iterations={self.iterations}, min_tracks="
              f"{self.min_tracks}, cell_px={self.cell_px} (expected >= 1)")
        check(min(self.pixel_sigma, self.robust_px, self.max_inconsistency, self.depth_log_std,
                  self.max_rotation_change_deg, self.max_length_change) > 0 and self.min_parallax_deg >= 0,
              "tracker.window: pixel_sigma, robust_px, max_inconsistency, depth_log_std, max_rotation_change_deg and "
              "max_length_change must be positive, min_parallax_deg >= 0")


@dataclass
class TrackerConfig:
    """Every setting of the odometry loop (:class:`dfvo.tracking.VisualOdometry`).

    Attributes:
        mode: see :class:`TrackerMode`.
        seed: frame k of a sequence draws its random samples from ``torch.Generator().manual_seed(seed + k)``.
        correspondence, essential, model_selection, scale, road_plane, road_alignment, camera_height, scale_filter,
            gate, pnp: the stages' sections. covariance: the per-frame covariance of the step. window: the
            sliding-window refinement of each step (off by default).
        motion: see :class:`MotionModel`; handheld: what a hand-held motion changes; motion_auto: how ``auto``
            judges it.
    """

    mode: TrackerMode = TrackerMode.hybrid
    seed: int = 0
    correspondence: SelectionConfig = field(default_factory=SelectionConfig)
    essential: EssentialConfig = field(default_factory=EssentialConfig)
    model_selection: ModelSelectionConfig = field(default_factory=ModelSelectionConfig)
    scale: ScaleConfig = field(default_factory=ScaleConfig)
    road_plane: RoadPlaneConfig = field(default_factory=RoadPlaneConfig)
    road_alignment: RoadAlignmentConfig = field(default_factory=RoadAlignmentConfig)
    camera_height: CameraHeightConfig = field(default_factory=CameraHeightConfig)
    scale_filter: ScaleFilterConfig = field(default_factory=ScaleFilterConfig)
    gate: GateConfig = field(default_factory=GateConfig)
    pnp: PnPConfig = field(default_factory=PnPConfig)
    covariance: CovarianceConfig = field(default_factory=CovarianceConfig)
    window: WindowConfig = field(default_factory=WindowConfig)
    motion: MotionModel = MotionModel.auto
    handheld: HandheldConfig = field(default_factory=HandheldConfig)
    motion_auto: MotionAutoConfig = field(default_factory=MotionAutoConfig)

    def __post_init__(self) -> None:
        self.mode = choice(TrackerMode, self.mode, "tracker.mode")
        self.motion = choice(MotionModel, self.motion, "tracker.motion")
