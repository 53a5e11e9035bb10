"""Network sources: trained flow and depth checkpoints, loaded safely (tensors only, no pickled code).

Checkpoint files are read by :mod:`dfvo.io.checkpoint` (``.safetensors``, or weights-only ``.pt``/``.ckpt``).

Network input size:
    A network runs best at the resolution it was trained at (a correlation layer's search range is in pixels;
    depth cues are learnt at one scale). ``input_size=(h, w)`` resizes the images to that size before the network
    and resizes its output back (flow vectors scaled by the size ratios); ``None`` takes the checkpoint's
    ``height``/``width`` metadata when it has them (the export script writes them), else the images' own size.

Convention:
    Images (B,3,H,W) float in [0,1]; flow (B,2,H,W) in pixels of the input; depth (B,1,H,W) in metres after
    multiplying the network depth by ``depth_scale`` (5.4 for a monodepth2-style stereo model trained with a
    0.1 baseline on KITTI's 0.54 m rig; 1.0 for models trained with the true baseline or monocular ones).
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from kornia.core.check import KORNIA_CHECK, KORNIA_CHECK_SHAPE

from dfvo.geometry.camera import resize_flow
from dfvo.io.checkpoint import CheckpointError, load_weights, read_state_dict
from dfvo.models.depth_net import DepthNet, network_width
from dfvo.models.flow_net import FlowNet
from dfvo.sources.config import DepthSourceConfig, RuntimeConfig, RuntimeKind

log = logging.getLogger(__name__)

__all__ = ["blend_flipped_inverse_depth", "NetworkFlow", "NetworkDepth", "resolve_input_size", "resize_images",
           "resize_flow"]

VARIANTS = ("default", "small", "tiny")


def resolve_input_size(input_size: Any, meta: dict[str, str], what: str) -> tuple[int, int] | None:
    """``(h, w)`` the network should see: ``input_size`` when given (a pair of positive ints), else the checkpoint
    metadata's ``height``/``width``, else None (the images' own size)."""
    if input_size is None:
        if "height" in meta and "width" in meta:
            return int(meta["height"]), int(meta["width"])
        return None
    try:
        h, w = (int(v) for v in input_size)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{what}.input_size={input_size!r}; expected [height, width] or null") from err
    if h < 32 or w < 32:
        raise ValueError(f"{what}.input_size={input_size!r}; expected [height, width] of at least 32 pixels")
    return h, w


def resize_images(images: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Images (B,C,H,W) -> ``size`` (h, w) as the networks see them: antialiased bilinear (unchanged at that size)."""
    if tuple(images.shape[-2:]) == size:
        return images
    return F.interpolate(images, size=size, mode="bilinear", align_corners=False, antialias=True)


class _Runtime:
    """The runtime that runs a source's network: PyTorch itself, or an exported model (:mod:`dfvo.sources.runtime`), one
    per network input size, exported on first use and checked against the checkpoint (stale exports are redone)."""

    def __init__(self, config: RuntimeConfig | None, what: str, device: torch.device) -> None:
        self.config = config or RuntimeConfig()
        self.kind = RuntimeKind(self.config.kind)
        self.auto = self.kind == RuntimeKind.auto  # a default: falls back to PyTorch where it cannot export (engine)
        self.reason = f"{what}.runtime.kind={self.kind.value}"
        if self.kind == RuntimeKind.auto:
            from dfvo.sources.runtime.engines import resolve_auto_runtime

            kind, precision, why = resolve_auto_runtime(str(device))
            self.config = dataclasses.replace(self.config, kind=RuntimeKind(kind), precision=precision)
            self.kind, self.reason = RuntimeKind(kind), f"{what}.runtime.kind=auto: {why}"
        self.what = what
        self.engines: dict[tuple[int, int], Any] = {}
        self.name = self.kind.value + ("" if self.config.precision == "fp32" else f"-{self.config.precision}")
        if self.kind != RuntimeKind.torch:
            from dfvo.sources.runtime.engines import require_runtime

            require_runtime(self.kind.value, f"{what}.runtime.kind")
            if device.type != "cpu":
                raise ValueError(f"{what}.runtime.kind={self.kind.value} runs on the CPU, not on device={device}; "
                                 f"use device=cpu or {what}.runtime.kind=torch")
        if self.kind != RuntimeKind.torch or self.config.precision != "fp32":
            from dfvo.sources.runtime.engines import check_precision

            check_precision(self.kind.value, self.config.precision, f"{what}.runtime.precision")

    def engine(self, spec: Any, model: torch.nn.Module) -> Any | None:
        """The engine of ``spec`` (an :class:`dfvo.sources.runtime.export.ExportSpec`), exported and built on first
        use (called only while ``kind`` is not ``torch``); None when ``auto`` could not write the export.

        ``kind=auto`` is a default, so a cache folder it cannot write (read-only home, a file in its place) makes it
        fall back to PyTorch fp32 (``kind`` becomes ``torch``) with one warning and the reason in ``reason``; a
        runtime asked for by name is refused instead (one line naming ``runtime.cache_dir``)."""
        if spec.input_size not in self.engines:
            from dfvo.sources.runtime.engines import build_engine
            from dfvo.sources.runtime.export import exported_model

            try:
                path = exported_model(spec, lambda: model, self.config.cache_dir, f"{self.what}.runtime.cache_dir")
            except OSError as err:
                if not self.auto:
                    raise
                log.warning("%s.runtime.kind=auto: %s; running the network on PyTorch fp32", self.what, err)
                self.kind, self.name = RuntimeKind.torch, RuntimeKind.torch.value
                self.reason = f"{self.reason}; the export failed ({err}): PyTorch fp32"
                return None
            self.engines[spec.input_size] = build_engine(self.kind.value, path, precision=self.config.precision)
        return self.engines[spec.input_size]


class NetworkFlow:
    """Forward and backward flow from a trained :class:`~dfvo.models.flow_net.FlowNet` (one batch of 2B pairs).

    Args:
        checkpoint: weights file.
        variant: FlowNet variant; None: the checkpoint's ``variant`` metadata, else the first of
            :data:`VARIANTS` whose parameters match the checkpoint.
        device: torch device.
        input_size: (h, w) the network runs at (see module docstring); None: checkpoint metadata or image size.
        runtime: what runs the network (None: PyTorch); see :mod:`dfvo.sources.runtime`.
    """

    name = "network"

    def __init__(self, checkpoint: str | Path, variant: str | None = None, device: str = "cpu",
                 input_size: Any = None, runtime: RuntimeConfig | None = None) -> None:
        self.checkpoint = Path(checkpoint)
        meta = {}
        if self.checkpoint.is_file():
            _, meta = read_state_dict(self.checkpoint, "flow network", "flow.checkpoint")
        if variant is None and "variant" not in meta and self.checkpoint.is_file():
            variant = self._guess_variant(device)
        self.variant = variant or meta.get("variant", "default")
        self.model = FlowNet(self.variant).to(device).eval()
        load_weights(self.model, self.checkpoint, f"flow network FlowNet({self.variant!r})", "flow.checkpoint")
        self.device = torch.device(device)
        self.input_size = resolve_input_size(input_size, meta, "flow")
        self._checked_output = False
        self._runtime = _Runtime(runtime, "flow", self.device)
        if self._runtime.kind != RuntimeKind.torch and self.input_size is not None:
            self._runtime.engine(self.export_spec(self.input_size), self.model)  # export now, not mid-run

    @property
    def runtime(self) -> str:
        """What runs the network: ``torch``, ``onnxruntime`` or ``openvino`` (``openvino-bf16`` in bf16)."""
        return self._runtime.name

    @property
    def runtime_reason(self) -> str:
        """Why this runtime: the setting, or what ``runtime.kind=auto`` found on this machine."""
        return self._runtime.reason

    def export_spec(self, input_size: tuple[int, int]) -> Any:
        """The :class:`dfvo.sources.runtime.export.ExportSpec` of this network at ``input_size`` (h, w)."""
        from dfvo.sources.runtime.export import ExportSpec

        return ExportSpec("flow", self.checkpoint, tuple(input_size), variant=self.variant)

    def forward_backward(self, img1: torch.Tensor, img2: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``FlowNet.forward_backward`` of images (B,3,h,w) already at the network's input size, by the runtime."""
        engine = (None if self._runtime.kind == RuntimeKind.torch
                  else self._runtime.engine(self.export_spec(tuple(img1.shape[-2:])), self.model))
        if engine is None:  # PyTorch: asked for, or auto's fallback
            return self.model.forward_backward(img1, img2)
        fwd, bwd = engine(img1, img2)
        return fwd.to(img1.device), bwd.to(img1.device)

    def _guess_variant(self, device: str) -> str | None:
        """The first FlowNet variant whose parameters the checkpoint holds (None: none does; load_weights then
        reports the mismatch against the default variant)."""
        for name in VARIANTS:
            try:
                load_weights(FlowNet(name).to(device), self.checkpoint, f"flow network FlowNet({name!r})")
                return name
            except CheckpointError:
                continue
        return None

    def network_inputs(self, *images: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """The images (B,3,H,W) as the network sees them: on its device, resized to its input size."""
        return tuple(resize_images(im.to(self.device), self.input_size or tuple(im.shape[-2:])) for im in images)

    def __call__(self, images_prev: torch.Tensor, images_cur: torch.Tensor,
                 indices: list[int] | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """``(flow_fwd, flow_bwd)`` (B,2,H,W) for images (B,3,H,W) prev and cur (``indices`` unused)."""
        KORNIA_CHECK_SHAPE(images_prev, ["B", "3", "H", "W"])
        size = tuple(images_prev.shape[-2:])
        with torch.no_grad():
            fwd, bwd = self.forward_backward(*self.network_inputs(images_prev, images_cur))
        if not self._checked_output:  # the first batch: finite weights can still give a NaN flow
            if not (torch.isfinite(fwd).all() and torch.isfinite(bwd).all()):
                raise CheckpointError(f"flow.checkpoint={self.checkpoint}: the network's flow of the first frames "
                                      "is NaN or inf; the weights are damaged or not a trained FlowNet: copy or export "
                                      "the checkpoint again")
            self._checked_output = True
        return resize_flow(fwd, size), resize_flow(bwd, size)


def blend_flipped_inverse_depth(inv_depth: torch.Tensor, inv_depth_of_mirror: torch.Tensor,
                                border: float = 0.05) -> torch.Tensor:
    """Blend a prediction with the prediction for the mirrored image (mirrored back), both (B,1,H,W) inverse depth.

    The mean of the two, except near the left and right borders: a stereo-trained network is unreliable on the
    strip of the left image its right partner does not see (the left border), so there the mirrored prediction
    (whose unreliable strip is on the other side) takes over, fading linearly to the mean between ``border`` and
    ``2 * border`` of the width; symmetrically at the right border (monodepth's post-processing).
    """
    KORNIA_CHECK_SHAPE(inv_depth, ["B", "1", "H", "W"])
    KORNIA_CHECK(inv_depth_of_mirror.shape == inv_depth.shape,
                 f"blend_flipped_inverse_depth: shapes {tuple(inv_depth.shape)} and "
                 f"{tuple(inv_depth_of_mirror.shape)} differ")
    KORNIA_CHECK(0.0 < border <= 0.25, f"blend_flipped_inverse_depth: border={border}; expected (0, 0.25]")
    w = inv_depth.shape[-1]
    u = torch.linspace(0.0, 1.0, w, dtype=inv_depth.dtype, device=inv_depth.device)
    near_left = (1.0 - ((u - border) / border).clamp(0.0, 1.0)).view(1, 1, 1, w)
    near_right = near_left.flip(-1)
    mean = 0.5 * (inv_depth + inv_depth_of_mirror)
    return near_right * inv_depth + near_left * inv_depth_of_mirror + (1.0 - near_left - near_right) * mean


class NetworkDepth:
    """Depth from a trained :class:`~dfvo.models.depth_net.DepthNet`.

    Args:
        checkpoint: weights file.
        depth_scale: factor from the network's depth to metres (see module docstring).
        min_depth, max_depth: the network's depth range (as trained).
        device: torch device.
        input_size: (h, w) the network runs at (see module docstring); None: checkpoint metadata or image size
            rounded to multiples of 32.
        flip_average: also run the network on the mirrored images and blend the two inverse depths (monodepth's
            test-time post-processing; see :func:`blend_flipped_inverse_depth`); twice the network time.
        runtime: what runs the network (None: PyTorch); see :mod:`dfvo.sources.runtime`.
    """

    name = "network"

    def __init__(self, checkpoint: str | Path, depth_scale: float = DepthSourceConfig.depth_scale,
                 min_depth: float = DepthSourceConfig.min_depth, max_depth: float = DepthSourceConfig.max_depth,
                 device: str = "cpu", input_size: Any = None,
                 flip_average: bool = DepthSourceConfig.flip_average, runtime: RuntimeConfig | None = None) -> None:
        if depth_scale <= 0:
            raise ValueError(f"depth.depth_scale={depth_scale}; expected a positive factor to metres")
        self.checkpoint = Path(checkpoint)
        # read once: the file sizes the network (its channel width) and fills it (a missing or unreadable file: one
        # clear error from read_state_dict, as load_weights would give)
        contents = read_state_dict(self.checkpoint, "depth network DepthNet", "depth.checkpoint")
        width = network_width(contents[1], "depth.checkpoint", contents[0])
        self.model = DepthNet(min_depth, max_depth, width=width).to(device).eval()
        meta = load_weights(self.model, self.checkpoint, "depth network DepthNet", "depth.checkpoint",
                            contents=contents)
        self.depth_scale = float(depth_scale)
        self.device = torch.device(device)
        self.input_size = resolve_input_size(input_size, meta, "depth")
        self.flip_average = bool(flip_average)
        self._runtime = _Runtime(runtime, "depth", self.device)
        if self._runtime.kind != RuntimeKind.torch and self.input_size is not None:
            self._runtime.engine(self.export_spec(self.network_size(*self.input_size)), self.model)

    @property
    def runtime(self) -> str:
        """What runs the network: ``torch``, ``onnxruntime`` or ``openvino`` (``openvino-bf16`` in bf16)."""
        return self._runtime.name

    @property
    def runtime_reason(self) -> str:
        """Why this runtime: the setting, or what ``runtime.kind=auto`` found on this machine."""
        return self._runtime.reason

    @staticmethod
    def network_size(h: int, w: int) -> tuple[int, int]:
        """The size the network runs at for a requested (h, w): multiples of 32, at least 64."""
        return max(64, round(h / 32) * 32), max(64, round(w / 32) * 32)

    def export_spec(self, input_size: tuple[int, int]) -> Any:
        """The :class:`dfvo.sources.runtime.export.ExportSpec` of this network at ``input_size`` (h, w; multiples of
        32)."""
        from dfvo.sources.runtime.export import ExportSpec

        return ExportSpec("depth", self.checkpoint, tuple(input_size), min_depth=self.model.min_depth,
                          max_depth=self.model.max_depth)

    def network_depth(self, inputs: torch.Tensor) -> torch.Tensor:
        """``DepthNet.depth`` (B,1,h,w) of images (B,3,h,w) already at the network's input size, by the runtime."""
        engine = (None if self._runtime.kind == RuntimeKind.torch
                  else self._runtime.engine(self.export_spec(tuple(inputs.shape[-2:])), self.model))
        if engine is None:  # PyTorch: asked for, or auto's fallback
            return self.model.depth(inputs)
        return engine(inputs)[0].to(inputs.device)

    def __call__(self, images: torch.Tensor, indices: list[int] | None = None) -> torch.Tensor:
        """Depth (B,1,H,W) in metres of images (B,3,H,W), computed at the network's input size (multiples of 32)
        and resized back."""
        KORNIA_CHECK_SHAPE(images, ["B", "3", "H", "W"])
        h, w = images.shape[-2:]
        hp, wp = self.network_size(*(self.input_size or (h, w)))
        with torch.no_grad():
            inputs = resize_images(images.to(self.device), (hp, wp))
            if self.flip_average:
                both = self.network_depth(torch.cat([inputs, inputs.flip(-1)]))
                plain, mirrored = both.split(inputs.shape[0])
                depth = 1.0 / blend_flipped_inverse_depth(1.0 / plain, 1.0 / mirrored.flip(-1))
            else:
                depth = self.network_depth(inputs)
            if (hp, wp) != (h, w):
                depth = F.interpolate(depth, size=(h, w), mode="bilinear", align_corners=False)
            return depth * self.depth_scale
