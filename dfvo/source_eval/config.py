"""Settings of ``dfvo-eval task=flow`` and ``task=depth``: the ``flow`` and ``depth`` nodes of the evaluate command.

The dataclasses are the single home of the defaults (the command's schema :class:`dfvo.cli.evaluate.EvaluateConfig`
holds them; no YAML repeats them). They reuse the inference settings instead of copying them:

- :class:`FlowEvalConfig` is a :class:`dfvo.sources.config.FlowSourceConfig` (``checkpoint``, ``variant``,
  ``input_size``, ``preset``, ``refine``: the same keys and meanings as ``infer.py``'s ``flow`` node) plus the
  benchmark's settings. Two inherited fields are declared again: ``source`` takes one more choice, ``pred``
  (prediction files), and ``oracle`` means the benchmark's own ground truth; ``refine`` defaults to no refinement
  (the network's own flow is scored unless ``flow.refine.iterations`` asks for ``infer.py``'s refinement).
- :class:`FlowSelectionEvalConfig` (``flow.selection``, the "+ BestN" rows) is the tracker's correspondence
  selection :class:`dfvo.tracking.config.SelectionConfig` plus the evaluation's ``threshold`` rule and N given as a
  fraction of the pixels (``num_correspondences: null``).
- :class:`DepthEvalConfig` holds the depth network's settings as ``depth.network``, a
  :class:`dfvo.sources.config.DepthSourceConfig` (``infer.py``'s ``depth`` node), because its ``min_depth`` /
  ``max_depth`` (the network's output range) differ from the evaluated range ``depth.min_depth`` /
  ``depth.max_depth``; ``depth.source`` chooses between the network and prediction files (``depth.network.source``
  is not read).

:func:`task_settings` turns a command's ``flow``/``depth`` node (typed by Hydra, or a plain mapping from Python) into
its dataclass; an unknown key or a bad value is a ``ValueError`` naming the key.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any, TypeVar

from omegaconf import OmegaConf
from omegaconf.errors import ConfigKeyError, OmegaConfBaseException

from dfvo.matching.flow_refinement import FlowRefinementConfig
from dfvo.sources.config import DepthSourceConfig, FlowSourceConfig
from dfvo.tracking.config import SelectionConfig

__all__ = ["FlowLayout", "FlowEvalSource", "EvalSelectionMethod", "DepthEvalSource", "DepthCrop",
           "FlowSelectionEvalConfig", "FlowEvalConfig", "DepthEvalConfig", "task_settings"]

T = TypeVar("T")


class FlowLayout(StrEnum):
    """KITTI flow layout of ``gt_dir`` (the ``training`` folder): ``kitti2015`` (images ``image_2/``) or
    ``kitti2012`` (images ``colored_0/``)."""

    kitti2015 = "kitti2015"
    kitti2012 = "kitti2012"


class FlowEvalSource(StrEnum):
    """``auto``: ``pred`` when ``pred_dir=`` is given, else ``network``; ``network``: the FlowNet of ``checkpoint``;
    ``dis``: OpenCV DIS (``preset``); ``oracle``: the ground truth itself (AEPE 0, a check of the plumbing);
    ``pred``: KITTI-format flow PNGs ``pred_dir/NNNNNN_10.png``."""

    auto = "auto"
    network = "network"
    dis = "dis"
    oracle = "oracle"
    pred = "pred"


class EvalSelectionMethod(StrEnum):
    """The tracker's methods (:class:`dfvo.tracking.config.SelectionMethod`) and ``threshold``: every pixel whose
    forward-backward inconsistency is under ``max_inconsistency``."""

    best_n = "best_n"
    local_best_k = "local_best_k"
    uniform = "uniform"
    threshold = "threshold"


class DepthEvalSource(StrEnum):
    """``auto``: ``pred`` when ``pred_dir=`` is given, else ``network``; ``network``: the DepthNet of
    ``network.checkpoint``; ``pred``: depth files under ``pred_dir`` (:mod:`dfvo.source_eval.depth`)."""

    auto = "auto"
    network = "network"
    pred = "pred"


class DepthCrop(StrEnum):
    """Evaluated image region: ``garg`` (Garg et al.'s crop), ``eigen`` (Eigen et al.'s), ``none``."""

    garg = "garg"
    eigen = "eigen"
    none = "none"


def _check(condition: bool, message: str) -> None:
    if not condition:
        raise ValueError(message)


@dataclass
class FlowSelectionEvalConfig(SelectionConfig):
    """The pixels of the "+ BestN" rows: the tracker's selection (every field of :class:`SelectionConfig`, same
    meaning) on the flows at the ground truth's size.

    Attributes:
        method: see :class:`EvalSelectionMethod`; ``best_n`` (the N most consistent pixels) by default, the paper's
            "+ BestN".
        num_correspondences: N; None: ``fraction * H * W`` of each image.
        fraction: N as a share of the pixels when ``num_correspondences`` is None (0.0163: DF-VO's N = 2000 at
            640x192).
    """

    method: EvalSelectionMethod = EvalSelectionMethod.best_n
    num_correspondences: int | None = None
    fraction: float = 0.0163

    def __post_init__(self) -> None:  # the tracker's checks, with this command's key names
        try:
            self.method = EvalSelectionMethod(getattr(self.method, "value", self.method))
        except ValueError:
            raise ValueError(f"flow.selection.method={self.method!r}; expected one of "
                             f"{[m.value for m in EvalSelectionMethod]}") from None
        _check(len(self.grid) == 2 and all(int(g) > 0 for g in self.grid),
               f"flow.selection.grid={list(self.grid)}; expected [rows, cols] of positive integers")
        self.grid = [int(g) for g in self.grid]
        _check(self.num_correspondences is None or int(self.num_correspondences) > 0,
               f"flow.selection.num_correspondences={self.num_correspondences}; expected a positive integer or null")
        _check(0.0 < float(self.fraction) <= 1.0, f"flow.selection.fraction={self.fraction}; expected (0, 1]")
        _check(self.max_inconsistency > 0, f"flow.selection.max_inconsistency={self.max_inconsistency}; expected > 0")
        _check(0.0 <= self.crop_top < 1.0, f"flow.selection.crop_top={self.crop_top}; expected [0, 1)")

    def num_for(self, height: int, width: int) -> int:
        """N for an image of ``height`` x ``width`` pixels."""
        if self.num_correspondences:
            return int(self.num_correspondences)
        return max(1, round(float(self.fraction) * height * width))


@dataclass
class FlowEvalConfig(FlowSourceConfig):
    """``dfvo-eval task=flow``: a flow source on a KITTI flow 2012/2015 training layout (:mod:`dfvo.source_eval.flow`).

    Attributes:
        source: see :class:`FlowEvalSource` (declared again: ``pred`` added, ``oracle`` is the ground truth).
        checkpoint, variant, input_size: ``source=network``, as in :class:`FlowSourceConfig`.
        preset: ``source=dis``: ``ultrafast`` | ``fast`` | ``medium``.
        refine: the photometric refinement of the network's flow, as ``infer.py`` applies it (declared again:
            none by default, ``iterations: 0``; ``flow.refine.iterations=2`` scores ``infer.py``'s refined flow).
        layout: see :class:`FlowLayout`.
        working_size: [h, w] the images are resized to before the source (e.g. [192, 640], ``infer.py``'s); None:
            native. The flow is resized back to the ground truth's size (vectors scaled).
        pred_bwd_dir: ``source=pred``: folder of backward flows ``NNNNNN_11.png`` (11 -> 10, on frame 11's pixels)
            for the "+ BestN" rows; None: look for them in ``pred_dir`` (those rows are null without them).
        fill_invalid: ``source=pred``: fill a sparse prediction's invalid pixels as the KITTI devkit does.
        frames: pair names to evaluate, e.g. ["000000", "000007"]; None: every pair with ground truth.
        max_pairs: evaluate only the first N pairs; None: all.
        thresholds: the Out-N columns in pixels (the paper reports Out-1).
        selection: the "+ BestN" rows' pixels (:class:`FlowSelectionEvalConfig`).
        device: where the source runs.
    """

    source: FlowEvalSource = FlowEvalSource.auto
    refine: FlowRefinementConfig = field(default_factory=lambda: FlowRefinementConfig(iterations=0))
    layout: FlowLayout = FlowLayout.kitti2015
    working_size: list[int] | None = None
    pred_bwd_dir: str | None = None
    fill_invalid: bool = True
    frames: list[str] | None = None
    max_pairs: int | None = None
    thresholds: list[float] = field(default_factory=lambda: [1.0, 3.0, 5.0])
    selection: FlowSelectionEvalConfig = field(default_factory=FlowSelectionEvalConfig)
    device: str = "cpu"

    def __post_init__(self) -> None:
        if self.working_size is not None:
            size = list(self.working_size)
            _check(len(size) == 2 and all(int(v) >= 8 for v in size),
                   f"flow.working_size={size!r}; expected [height, width] of at least 8 pixels, or null")
            self.working_size = [int(v) for v in size]
        _check(len(self.thresholds) > 0 and all(float(t) > 0 for t in self.thresholds),
               f"flow.thresholds={list(self.thresholds)}; expected Out-N thresholds in pixels > 0")


@dataclass
class DepthEvalConfig:
    """``dfvo-eval task=depth``: depth on the KITTI Eigen split or any KITTI raw frames (:mod:`dfvo.source_eval.depth`).

    Attributes:
        split: split file, lines ``2011_09_26/2011_09_26_drive_0002_sync 0000000069 l`` (``l``: image_02, ``r``:
            image_03); None: every frame with a velodyne scan under ``gt_dir``.
        source: see :class:`DepthEvalSource`.
        network: ``source=network``: the DepthNet (:class:`DepthSourceConfig`: ``checkpoint``, ``depth_scale``
            network depth -> metres (5.4 for a monodepth2 stereo model), ``min_depth``/``max_depth`` its output range,
            ``input_size``, ``flip_average``); its ``source`` is not read.
        min_depth, max_depth: the evaluated ground-truth range in metres; predictions are clamped to it.
        crop: see :class:`DepthCrop`.
        median_scaling: scale each prediction by median(gt) / median(pred) (monocular, up-to-scale models).
        gt_pixel_offset: 0: a point projecting to (u, v) lands on pixel (round(u), round(v)); -1 reproduces the
            published Eigen ground truth (monodepth's ``generate_depth_map``: round(u) - 1).
        max_frames: evaluate only the first N frames; None: all.
        device: where the network runs.
    """

    split: str | None = None
    source: DepthEvalSource = DepthEvalSource.auto
    network: DepthSourceConfig = field(default_factory=DepthSourceConfig)
    min_depth: float = 1e-3
    max_depth: float = 80.0
    crop: DepthCrop = DepthCrop.garg
    median_scaling: bool = False
    gt_pixel_offset: int = 0
    max_frames: int | None = None
    device: str = "cpu"

    def __post_init__(self) -> None:
        _check(0 < float(self.min_depth) < float(self.max_depth),
               f"depth.min_depth={self.min_depth}, depth.max_depth={self.max_depth}; expected 0 < min < max")


def task_settings(schema: type[T], cfg: Any, node: str) -> T:
    """``cfg[node]`` (a command config or a mapping; missing: the defaults) as a ``schema`` instance.

    Raises:
        ValueError: an unknown key or a value of the wrong type or choice; the message names ``node.key``.
    """
    given = cfg.get(node) if cfg is not None else None
    base = OmegaConf.structured(schema)
    try:
        return OmegaConf.to_object(OmegaConf.merge(base, given) if given is not None else base)
    except ConfigKeyError as err:
        parent = str(err.full_key).rpartition(".")[0]
        keys = sorted(OmegaConf.select(base, parent) if parent else base)
        raise ValueError(f"{node}.{err.full_key}: unknown setting; the settings of {node}"
                         f"{'.' + parent if parent else ''} are {keys}") from None
    except OmegaConfBaseException as err:
        reason = str(err).splitlines()[0]
        raise ValueError(f"{node}.{err.full_key}={err.value!r}: {reason}") from None
