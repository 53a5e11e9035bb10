"""Settings of the flow and depth sources (the ``flow`` and ``depth`` nodes of ``infer.py``'s config).

The dataclasses are the single home of the defaults; ``dfvo/conf/infer/flow/*.yaml`` and ``depth/*.yaml`` only
choose ``source`` (and what differs from these defaults).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum

from dfvo.matching.flow_refinement import FlowRefinementConfig
from dfvo.validation import check

__all__ = ["FlowSourceKind", "DepthSourceKind", "DisPreset", "RuntimeKind", "RuntimeConfig", "FlowSourceConfig",
           "DepthSourceConfig"]


class FlowSourceKind(StrEnum):
    """``auto``: the network when its checkpoint exists, else the oracle on synthetic data; ``network``: a trained
    FlowNet; ``oracle``: the synthetic world's true flow; ``dis``: OpenCV's DIS (the classical baseline)."""

    auto = "auto"
    network = "network"
    oracle = "oracle"
    dis = "dis"


class DepthSourceKind(StrEnum):
    """``auto``: the network when its checkpoint exists, else the oracle on synthetic data; ``network``: a trained
    DepthNet; ``oracle``: the synthetic world's true depth."""

    auto = "auto"
    network = "network"
    oracle = "oracle"


class DisPreset(StrEnum):
    """OpenCV DIS presets offered by ``flow.preset`` (``flow=dis``)."""

    ultrafast = "ultrafast"
    fast = "fast"
    medium = "medium"


class RuntimeKind(StrEnum):
    """What runs a network: ``torch`` (PyTorch eager, always available: the fallback), ``onnxruntime`` or
    ``openvino`` (the network exported to ONNX from its checkpoint and run by that library on the CPU; both come
    with the ``fast`` extra, ``pip install "dfvo[fast]"``; :mod:`dfvo.sources.runtime`), or ``auto``: OpenVINO in
    bf16 where the CPU has bf16 units (AVX512-BF16 or AMX, read from its flags) and the extra is installed, PyTorch
    in fp32 elsewhere (:func:`dfvo.sources.runtime.engines.resolve_auto_runtime`; the choice and its reason go into
    ``summary.json``)."""

    torch = "torch"
    onnxruntime = "onnxruntime"
    openvino = "openvino"
    auto = "auto"


@dataclass
class RuntimeConfig:
    """How a network source runs its network (``flow.runtime`` / ``depth.runtime``; ``runtime=openvino`` sets both).

    Attributes:
        kind: see :class:`RuntimeKind`.
        precision: ``fp32``, or ``bf16`` (``openvino`` only, on CPUs with bf16 instructions: AVX512-BF16 or AMX,
            read from the CPU's flags; about half the time of fp32 there, outputs within ~0.5 % of fp32:
            ``docs/speed.md``); ``kind=auto`` chooses it with the runtime.
        cache_dir: folder of the exported models (made from the checkpoint on first use and checked against it on
            every later use); None: ``$DFVO_CACHE_DIR/runtime``, else ``~/.cache/dfvo/runtime``.
    """

    kind: RuntimeKind = RuntimeKind.torch
    precision: str = "fp32"
    cache_dir: str | None = None


@dataclass
class FlowSourceConfig:
    """Where forward and backward flow come from.

    Attributes:
        source: see :class:`FlowSourceKind`.
        checkpoint: network weights (``.safetensors``/``.pt``/``.ckpt``); a relative path is looked up in the working
            folder, then among the package's shipped ``checkpoints/``.
        variant: FlowNet variant; None: the checkpoint's metadata.
        input_size: [h, w] the network runs at; None: the checkpoint's metadata, else the working size.
        preset: ``dis`` only: OpenCV DIS preset ``ultrafast``, ``fast`` or ``medium``.
        refine: photometric sub-pixel refinement applied to the network's flow (never to oracle or DIS flow).
        runtime: what runs the network (PyTorch, ONNX Runtime, OpenVINO); see :class:`RuntimeConfig`.
    """

    source: FlowSourceKind = FlowSourceKind.auto
    checkpoint: str = "checkpoints/flow.safetensors"
    variant: str | None = None
    input_size: list[int] | None = None
    preset: DisPreset = DisPreset.medium
    refine: FlowRefinementConfig = field(default_factory=FlowRefinementConfig)
    runtime: RuntimeConfig = field(default_factory=RuntimeConfig)


@dataclass
class DepthSourceConfig:
    """Where depth comes from.

    Attributes:
        source: see :class:`DepthSourceKind`.
        checkpoint: network weights (see :class:`FlowSourceConfig`).
        depth_scale: network depth → metres (1.0 for models trained with the true stereo baseline).
        min_depth, max_depth: the network's depth range (metres).
        input_size: [h, w] the network runs at; None: the checkpoint's metadata, else the working size.
        flip_average: also run on the mirrored image and blend the inverse depths (2x depth time).
        runtime: what runs the network; see :class:`RuntimeConfig`.
        every: depth on every k-th frame only (1: every frame; k >= 2 needs ``tracker.scale.depth_views=2``: the
            frames between have none and each pair takes its scale, road plane and PnP points from its frame with
            depth; :mod:`dfvo.sources.every_kth`).
    """

    source: DepthSourceKind = DepthSourceKind.auto
    checkpoint: str = "checkpoints/depth.safetensors"
    depth_scale: float = 1.0
    min_depth: float = 0.1
    max_depth: float = 100.0
    input_size: list[int] | None = None
    flip_average: bool = False
    runtime: RuntimeConfig = field(default_factory=RuntimeConfig)
    every: int = 1

    def __post_init__(self) -> None:
        check(int(self.every) >= 1, f"depth.every={self.every}; expected a positive number of frames (1: every frame)")
