"""Depth network: ResNet-18 encoder + decoder with skip connections, sigmoid disparities at 4 scales.

Convention:
    Input (B,3,H,W) RGB in [0,1], H and W multiples of 32. Output dict ``{s: (B,1,H/2^s,W/2^s)}`` for
    s = 0..3, sigmoid "disparities" in (0,1) that :func:`disp_to_depth` maps to depth in
    [min_depth, max_depth]. A stereo-trained model (``model=depth_stereo``, trained with the true baseline
    of the calibration) outputs metres; a monocular one is up to an unknown scale.

Inference:
    :meth:`DepthNet.depth` / :meth:`DepthNet.disparity` compute only the scale-0 head. In eval mode without
    autograd they run a cached inference copy of the network: the encoder's batch norms folded into its
    convolutions (:func:`fold_batch_norms`) and all weights in channels_last memory format, oneDNN's fast layout
    on CPU (max pooling alone is ~20x faster than in NCHW). The copy is rebuilt when a weight changes or
    ``train()`` / ``eval()`` is called. The results equal the training forward's scale-0 output up to float
    rounding (~1e-7).
"""

from __future__ import annotations

import copy
import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from kornia.core.check import KORNIA_CHECK_SHAPE
from torch import nn

from dfvo.io.checkpoint import PREFIXES
from dfvo.models.resnet import BasicBlock, ResNet18Encoder, scaled_channels

DECODER_CHANNELS = (16, 32, 64, 128, 256)
SCALES = (0, 1, 2, 3)


def disp_to_depth(disp: torch.Tensor, min_depth: float = 0.1, max_depth: float = 100.0) -> torch.Tensor:
    """Map a sigmoid output in [0,1] to depth: ``1 / (1/max + (1/min - 1/max) * disp)``.

    Args:
        disp: (B,1,H,W) sigmoid disparity.
        min_depth, max_depth: depth at ``disp = 1`` and ``disp = 0``.

    Returns:
        (B,1,H,W) depth in [min_depth, max_depth] (metres for a stereo-trained model).
    """
    if not 0 < min_depth < max_depth:
        raise ValueError(f"disp_to_depth: expected 0 < min_depth < max_depth, got {min_depth}, {max_depth}")
    min_disp, max_disp = 1.0 / max_depth, 1.0 / min_depth
    return 1.0 / (min_disp + (max_disp - min_disp) * disp)


def _fold_bn(conv: nn.Conv2d, bn: nn.BatchNorm2d) -> None:
    """Fold ``bn`` (eval mode: running statistics) into ``conv`` in place, so that ``conv(x) == bn(conv(x))``."""
    scale = bn.weight * torch.rsqrt(bn.running_var + bn.eps)  # (C_out,)
    bias = bn.bias - bn.running_mean * scale
    if conv.bias is not None:
        bias = bias + conv.bias * scale
    conv.weight = nn.Parameter(conv.weight * scale[:, None, None, None], requires_grad=False)
    conv.bias = nn.Parameter(bias, requires_grad=False)


@torch.no_grad()
def fold_batch_norms(encoder: ResNet18Encoder) -> ResNet18Encoder:
    """Inference copy of ``encoder`` whose batch norms (eval mode) are folded into the preceding convolutions.

    The copy computes the same features as ``encoder.eval()`` up to float rounding, without the batch-norm
    passes; its batch norms are replaced by identities, its parameters need no gradients. ``encoder`` itself is
    not modified. Shapes as :class:`~dfvo.models.resnet.ResNet18Encoder`.
    """
    fused = copy.deepcopy(encoder).eval().requires_grad_(False)
    _fold_bn(fused.conv1, fused.bn1)
    fused.bn1 = nn.Identity()
    for block in fused.modules():
        if isinstance(block, BasicBlock):
            _fold_bn(block.conv1, block.bn1)
            _fold_bn(block.conv2, block.bn2)
            block.bn1, block.bn2 = nn.Identity(), nn.Identity()
            if block.downsample is not None:
                _fold_bn(block.downsample[0], block.downsample[1])
                block.downsample = block.downsample[0]
    if any(isinstance(m, nn.modules.batchnorm._BatchNorm) for m in fused.modules()):
        raise TypeError("fold_batch_norms: the encoder holds a batch norm that this function does not fold")
    return fused


def network_width(meta: dict[str, str], setting: str, state: dict[str, torch.Tensor] | None = None) -> float:
    """The channel multiplier (``DepthNet(width=...)``) of a weights file: its metadata's ``width_multiplier``; without
    one (a training checkpoint, a plain state dict, a file written before narrower networks existed) the encoder's
    first layer in ``state`` (its output channels over 64), else 1. ``setting`` names the file's config key in the
    one-line error for a value that is not a positive number."""
    raw = meta.get("width_multiplier")
    if raw is None:  # the depth network's own first layer, under the prefixes load_weights knows (a training
        # checkpoint holds the pose network's encoder too: "depth_net." comes before "pose_net." there)
        keys = [p + "encoder.conv1.weight" for p in PREFIXES if p + "encoder.conv1.weight" in (state or {})]
        return state[keys[0]].shape[0] / 64.0 if keys else 1.0
    try:
        width = float(raw)
    except ValueError:
        width = float("nan")
    if not width > 0 or not math.isfinite(width):
        raise ValueError(f"{setting}: the file's width_multiplier metadata is {raw!r}; expected a positive number")
    return width


class ConvBlock(nn.Module):
    """3x3 convolution with reflection padding followed by ELU."""

    def __init__(self, in_ch: int, out_ch: int, activation: bool = True) -> None:
        super().__init__()
        self.pad = nn.ReflectionPad2d(1)
        self.conv = nn.Conv2d(in_ch, out_ch, 3)
        self.act = nn.ELU(inplace=True) if activation else nn.Identity()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.act(self.conv(self.pad(x)))


class DepthDecoder(nn.Module):
    """U-Net style decoder over the 5 ResNet feature maps; disparity heads at scales 0..3.

    Args:
        num_ch_enc: the encoder maps' channels (finest first). channels: the decoder's 5 levels' channels (finest
            first; :data:`DECODER_CHANNELS` for the monodepth2 network, scaled by ``DepthNet(width=...)``).
    """

    def __init__(self, num_ch_enc: tuple[int, ...], channels: tuple[int, ...]) -> None:
        super().__init__()
        self.up0 = nn.ModuleList()
        self.up1 = nn.ModuleList()
        for i in range(5):
            in_ch = num_ch_enc[-1] if i == 4 else channels[i + 1]
            self.up0.append(ConvBlock(in_ch, channels[i]))
            skip = num_ch_enc[i - 1] if i > 0 else 0
            self.up1.append(ConvBlock(channels[i] + skip, channels[i]))
        self.heads = nn.ModuleList([ConvBlock(channels[s], 1, activation=False) for s in SCALES])

    def forward(self, features: list[torch.Tensor], scales: Sequence[int] = SCALES) -> dict[int, torch.Tensor]:
        """Disparities at ``scales`` from the encoder features.

        Args:
            features: the 5 encoder maps (B,64,H/2,W/2) ... (B,512,H/32,W/32), any memory format.
            scales: subset of :data:`SCALES` to compute; the heads of the other scales are skipped (and the
                levels below the finest requested scale, when 0 is not requested).

        Returns:
            dict scale -> (B,1,H/2^s,W/2^s) sigmoid disparity, for each scale in ``scales``.
        """
        if not scales or not set(scales) <= set(SCALES):
            raise ValueError(f"DepthDecoder: scales must be a non-empty subset of {SCALES}, got {tuple(scales)}")
        out: dict[int, torch.Tensor] = {}
        x = features[-1]
        for i in range(4, min(scales) - 1, -1):
            x = F.interpolate(self.up0[i](x), scale_factor=2, mode="nearest")
            if i > 0:
                x = torch.cat([x, features[i - 1]], dim=1)
            x = self.up1[i](x)
            if i in scales:
                # the heads in float32 under autocast (bf16 training): bf16's 8-bit mantissa would quantise the
                # disparity logits by ~1-2 % of the depth
                with torch.autocast(x.device.type, enabled=False):
                    out[i] = torch.sigmoid(self.heads[i](x.float()))
        return out


class DepthNet(nn.Module):
    """Monocular depth network (monodepth2-style architecture).

    Args:
        min_depth, max_depth: depth range of :meth:`depth`.
        init_depth: if given, the disparity heads start (bias) at the disparity of this depth, so that an
            untrained stereo model predicts a plausible metric depth: with the sigmoid at 0.5 the initial
            depth would be ~0.2 m, whose stereo disparity (fx * b / z, ~500 px at 320 px width) leaves the
            image and gives the stereo term no gradient.
        width: channel multiplier of the encoder and the decoder (:func:`~dfvo.models.resnet.scaled_channels`);
            1 is the monodepth2 network, 0.5 a cheaper one with about a quarter of its multiply-adds. Files
            record it (metadata ``width_multiplier``, :func:`network_width`).

    Shape:
        - Input: (B,3,H,W), H, W multiples of 32.
        - Output of ``forward``: dict scale -> (B,1,H/2^s,W/2^s) disparity in (0,1), scales 0..3.
    """

    def __init__(self, min_depth: float = 0.1, max_depth: float = 100.0, init_depth: float | None = None,
                 width: float = 1.0) -> None:
        super().__init__()
        self.min_depth, self.max_depth = float(min_depth), float(max_depth)
        self.width = float(width)
        self.encoder = ResNet18Encoder(1, width)
        self.decoder = DepthDecoder(self.encoder.num_ch_enc, scaled_channels(DECODER_CHANNELS, width))
        # (weights key, encoder, decoder) inference copy of :meth:`disparity`; not part of the state dict
        self._inference_cache: tuple[tuple, ResNet18Encoder, DepthDecoder] | None = None
        if init_depth is not None:
            if not self.min_depth < init_depth < self.max_depth:
                raise ValueError(f"DepthNet: init_depth {init_depth} outside ({min_depth}, {max_depth})")
            disp = (1.0 / init_depth - 1.0 / self.max_depth) / (1.0 / self.min_depth - 1.0 / self.max_depth)
            with torch.no_grad():
                for head in self.decoder.heads:
                    head.conv.bias.fill_(math.log(disp / (1.0 - disp)))

    def forward(self, image: torch.Tensor) -> dict[int, torch.Tensor]:
        """Training forward: dict scale -> (B,1,H/2^s,W/2^s) disparity for scales 0..3 of ``image`` (B,3,H,W)."""
        KORNIA_CHECK_SHAPE(image, ["B", "3", "H", "W"])
        return self.decoder(self.encoder(image))

    def train(self, mode: bool = True) -> DepthNet:
        """Set the training mode (see :meth:`torch.nn.Module.train`); drops the cached inference copy."""
        self._inference_cache = None
        return super().train(mode)

    def _weights_key(self) -> tuple | None:
        """Identity and version of every parameter and buffer, or None when untrackable (inference tensors)."""
        tensors = [*self.parameters(), *self.buffers()]
        if any(t.is_inference() for t in tensors):
            return None
        return tuple((id(t), t.data_ptr(), t._version, t.dtype, t.device) for t in tensors)

    def _inference_modules(self) -> tuple[ResNet18Encoder, DepthDecoder]:
        """(encoder, decoder) inference copy of the network, built on first use and cached.

        The encoder has its batch norms folded in (:func:`fold_batch_norms`); both are in channels_last format
        and need no gradients. The copy is rebuilt when a parameter or buffer changes (in-place update,
        ``load_state_dict``, ``to``) and dropped by :meth:`train` / ``eval``.
        """
        key = self._weights_key()
        cache = getattr(self, "_inference_cache", None)
        if key is None or cache is None or cache[0] != key:
            with torch.no_grad():
                encoder = fold_batch_norms(self.encoder).to(memory_format=torch.channels_last)
                decoder = copy.deepcopy(self.decoder).requires_grad_(False).to(memory_format=torch.channels_last)
            cache = (key, encoder, decoder)
            self._inference_cache = cache if key is not None else None
        return cache[1], cache[2]

    def disparity(self, image: torch.Tensor) -> torch.Tensor:
        """Full-resolution (scale 0) disparity of ``image``, the inference path: only the scale-0 head runs.

        In eval mode without autograd (``torch.no_grad`` / ``torch.inference_mode``) it runs the cached inference
        copy (batch norms folded into the encoder's convolutions, channels_last format); otherwise (training mode or
        gradients enabled) it is the training forward restricted to scale 0. Either way the result equals
        ``self(image)[0]`` up to float rounding.

        Args:
            image: (B,3,H,W) RGB in [0,1], H and W multiples of 32.

        Returns:
            (B,1,H,W) contiguous sigmoid disparity in (0,1).
        """
        KORNIA_CHECK_SHAPE(image, ["B", "3", "H", "W"])
        if self.training or torch.is_grad_enabled():
            return self.decoder(self.encoder(image), scales=(0,))[0]
        encoder, decoder = self._inference_modules()
        features = encoder(image.contiguous(memory_format=torch.channels_last))
        return decoder(features, scales=(0,))[0].contiguous()

    @torch.no_grad()
    def depth(self, image: torch.Tensor) -> torch.Tensor:
        """Full-resolution depth (B,1,H,W) of ``image`` (B,3,H,W) in [min_depth, max_depth] (see :meth:`disparity`)."""
        return disp_to_depth(self.disparity(image), self.min_depth, self.max_depth)
