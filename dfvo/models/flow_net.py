"""LiteFlowNet-style optical flow network (Hui et al. 2018), written for CPU-friendly plain PyTorch.

Structure: a feature pyramid shared by both images; coarse-to-fine cascaded flow inference where each
pyramid level runs (M) a matching step on a correlation cost volume between the first image's features
and the second image's features warped by the upsampled flow, (S) a sub-pixel refinement on the warped
features, and (R) a regularisation step that smooths the flow with per-pixel learnt local kernels (a
feature-driven local convolution) guided by features, flow and the brightness error.

Convention:
    - Images (B,3,H,W) float in [0,1]. Flow (B,2,H,W) in pixels of the input images:
      ``flow_1→2(x)`` = position in image 2 of pixel ``x`` of image 1 minus ``x`` (dfvo convention).
    - Inside the network images are resized (bilinear, ``align_corners=False``) to the nearest multiple of
      32 in each dimension; flows are resized back and their u/v components rescaled by ``W/W'``, ``H/H'``.
    - Multi-scale outputs (``all_scales=True``) are returned finest first, each upsampled to the input
      size in input pixels: scale ``s = 1..S`` comes from the pyramid level of stride ``2**(s + finest_level - 1)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from kornia.core.check import KORNIA_CHECK, KORNIA_CHECK_SHAPE
from torch import nn

from dfvo.geometry.camera import resize_flow
from dfvo.matching.flow_warp import warp_by_flow
from dfvo.models.correlation import correlation

MULTIPLE = 32


@dataclass
class FlowNetConfig:
    """Size of the network.

    Attributes:
        channels: feature channels of pyramid levels 1.. (level l has stride 2**l); its length is the
            number of levels.
        finest_level: finest level at which flow is inferred (2 = stride 4, as LiteFlowNet); the output is
            upsampled from there.
        search_range: correlation radius per inferred level, coarsest first (one int = same everywhere).
        decoder_width: hidden channels of the matching/sub-pixel/regularisation conv stacks, per inferred
            level, coarsest first (one int = same everywhere). The finest level dominates the cost.
        reg_kernel: size of the regularisation kernel (odd).
    """

    channels: tuple[int, ...] = (24, 32, 64, 96, 128, 160)
    finest_level: int = 2
    search_range: tuple[int, ...] | int = (3, 3, 3, 3, 3)
    decoder_width: tuple[int, ...] | int = (96, 96, 64, 64, 32)
    reg_kernel: int = 3

    @staticmethod
    def variant(name: str) -> FlowNetConfig:
        """Named sizes: ``"default"`` (6 levels, flow at stride 4..64) and ``"small"`` (5 levels, CPU)."""
        if name == "default":
            return FlowNetConfig()
        if name == "small":
            return FlowNetConfig(channels=(16, 24, 32, 48, 64), search_range=(3, 3, 2, 2), decoder_width=32)
        if name == "tiny":
            return FlowNetConfig(channels=(8, 16, 24, 32), search_range=(3, 2, 2), decoder_width=16)
        raise ValueError(f"FlowNetConfig.variant: unknown variant {name!r}; expected 'default', 'small' or 'tiny'")


def _conv(cin: int, cout: int, stride: int = 1, act: bool = True) -> nn.Module:
    layers: list[nn.Module] = [nn.Conv2d(cin, cout, 3, stride, 1)]
    if act:
        layers.append(nn.LeakyReLU(0.1, inplace=True))
    return nn.Sequential(*layers)


def _init_weights(module: nn.Module) -> None:
    """He initialisation for leaky-ReLU convs (keeps feature magnitudes, so the cost volume is informative)."""
    for m in module.modules():
        if isinstance(m, nn.Conv2d):
            nn.init.kaiming_normal_(m.weight, a=0.1, nonlinearity="leaky_relu")
            nn.init.zeros_(m.bias)


def _flow_head(cin: int, width: int, cout: int = 2) -> nn.Sequential:
    head = nn.Sequential(_conv(cin, width), _conv(width, width), _conv(width, width // 2),
                         nn.Conv2d(width // 2, cout, 3, 1, 1))
    nn.init.zeros_(head[-1].weight)
    nn.init.zeros_(head[-1].bias)
    return head


class FeaturePyramid(nn.Module):
    """Two 3x3 convs per level, the first with stride 2: level l has stride 2**l."""

    def __init__(self, channels: tuple[int, ...]) -> None:
        super().__init__()
        cin = 3
        self.levels = nn.ModuleList()
        for c in channels:
            self.levels.append(nn.Sequential(_conv(cin, c, stride=2), _conv(c, c)))
            cin = c

    def forward(self, image: torch.Tensor) -> list[torch.Tensor]:
        feats = []
        x = image
        for level in self.levels:
            x = level(x)
            feats.append(x)
        return feats


class CascadeLevel(nn.Module):
    """Flow inference at one pyramid level: matching (M), sub-pixel refinement (S), regularisation (R)."""

    def __init__(self, channels: int, search_range: int, width: int, reg_kernel: int) -> None:
        super().__init__()
        self.search_range = search_range
        self.reg_kernel = reg_kernel
        ncost = (2 * search_range + 1) ** 2
        red = min(channels, 32)
        self.reduce = nn.Conv2d(channels, red, 1)
        self.match = _flow_head(ncost + red + 2, width)
        self.subpixel = _flow_head(2 * channels + 2, width)
        self.reg_feat = nn.Sequential(_conv(red + 2 + 1, width), _conv(width, width), _conv(width, width // 2),
                                      nn.Conv2d(width // 2, reg_kernel * reg_kernel, 3, 1, 1))

    def forward(self, f1: torch.Tensor, f2: torch.Tensor, img1: torch.Tensor, img2: torch.Tensor,
                flow: torch.Tensor) -> torch.Tensor:
        """Refine ``flow`` (B,2,h,w) in level pixels given level features and level-size images."""
        f1r = F.leaky_relu(self.reduce(f1), 0.1)
        warped, _ = warp_by_flow(f2, flow)
        cost = F.leaky_relu(correlation(f1, warped, self.search_range), 0.1)
        flow = flow + self.match(torch.cat([cost, f1r, flow], 1))
        warped, _ = warp_by_flow(f2, flow)
        flow = flow + self.subpixel(torch.cat([f1, warped, flow], 1))
        # Regularisation: per-pixel softmax kernels over the k x k neighbourhood of the flow.
        img_warped, _ = warp_by_flow(img2, flow)
        brightness = (img1 - img_warped).abs().mean(1, keepdim=True)
        mean_flow = flow.mean(dim=(2, 3), keepdim=True)
        logits = self.reg_feat(torch.cat([f1r, flow - mean_flow, brightness], 1))
        weights = torch.softmax(logits, dim=1)  # (B,k*k,h,w)
        k = self.reg_kernel
        b, _, h, w = flow.shape
        patches = F.unfold(F.pad(flow, (k // 2,) * 4, mode="replicate"), k).view(b, 2, k * k, h, w)
        return (patches * weights.unsqueeze(1)).sum(2)


class FlowNet(nn.Module):
    """LiteFlowNet-style flow network.

    Args:
        config: a ``FlowNetConfig`` or a variant name (``"default"``, ``"small"``, ``"tiny"``).

    Example:
        >>> net = FlowNet("small")
        >>> flow_fwd, flow_bwd = net.forward_backward(img1, img2)  # each (B,2,H,W)
    """

    def __init__(self, config: FlowNetConfig | str = "default") -> None:
        super().__init__()
        cfg = FlowNetConfig.variant(config) if isinstance(config, str) else config
        self.config = cfg
        nlev = len(cfg.channels)
        KORNIA_CHECK(1 <= cfg.finest_level <= nlev,
                     f"FlowNetConfig.finest_level must be in [1, {nlev}], got {cfg.finest_level}")
        self.inferred_levels = list(range(nlev, cfg.finest_level - 1, -1))  # coarsest first
        n = len(self.inferred_levels)
        sr = [cfg.search_range] * n if isinstance(cfg.search_range, int) else list(cfg.search_range)
        widths = [cfg.decoder_width] * n if isinstance(cfg.decoder_width, int) else list(cfg.decoder_width)
        for name, values in (("search_range", sr), ("decoder_width", widths)):
            KORNIA_CHECK(len(values) == n, f"FlowNetConfig.{name} needs {n} entries (one per inferred level, "
                                           f"coarsest first), got {len(values)}")
        self.pyramid = FeaturePyramid(tuple(cfg.channels))
        self.cascade = nn.ModuleList(
            CascadeLevel(cfg.channels[lev - 1], r, width, cfg.reg_kernel)
            for lev, r, width in zip(self.inferred_levels, sr, widths))
        _init_weights(self)
        for block in self.cascade:  # residual flow heads start at zero: the initial flow is 0
            for head in (block.match, block.subpixel):
                nn.init.zeros_(head[-1].weight)

    @property
    def num_scales(self) -> int:
        """Number of multi-scale outputs (one per inferred pyramid level)."""
        return len(self.inferred_levels)

    def _infer(self, feats1: list[torch.Tensor], feats2: list[torch.Tensor], img1: torch.Tensor,
               img2: torch.Tensor) -> list[torch.Tensor]:
        """Coarse-to-fine cascade; returns per-level flows in level pixels, finest first."""
        flows: list[torch.Tensor] = []
        flow = None
        for lev, block in zip(self.inferred_levels, self.cascade):
            f1, f2 = feats1[lev - 1], feats2[lev - 1]
            size = f1.shape[-2:]
            flow = f1.new_zeros(f1.shape[0], 2, *size) if flow is None else resize_flow(flow, size)
            i1 = F.interpolate(img1, size=size, mode="area")
            i2 = F.interpolate(img2, size=size, mode="area")
            flow = block(f1, f2, i1, i2, flow)
            flows.append(flow)
        return flows[::-1]

    def _run(self, img1: torch.Tensor, img2: torch.Tensor, pairs_swapped: bool,
             all_scales: bool) -> list[torch.Tensor]:
        KORNIA_CHECK_SHAPE(img1, ["B", "3", "H", "W"])
        KORNIA_CHECK_SHAPE(img2, ["B", "3", "H", "W"])
        KORNIA_CHECK(img1.shape == img2.shape,
                     f"FlowNet: img1 {tuple(img1.shape)} and img2 {tuple(img2.shape)} must have the same shape")
        h, w = img1.shape[-2:]
        hp, wp = (max(MULTIPLE, math.ceil(h / MULTIPLE) * MULTIPLE), max(MULTIPLE, math.ceil(w / MULTIPLE) * MULTIPLE))
        both = torch.cat([img1, img2], 0)
        if (hp, wp) != (h, w):
            both = F.interpolate(both, size=(hp, wp), mode="bilinear", align_corners=False)
        feats = self.pyramid(both)
        b = img1.shape[0]
        a, c = both[:b], both[b:]
        if pairs_swapped:  # forward pairs (1,2) and backward pairs (2,1) in one batch of 2B
            feats1 = feats
            feats2 = [torch.cat([f[b:], f[:b]], 0) for f in feats]
            i1, i2 = both, torch.cat([c, a], 0)
        else:
            feats1 = [f[:b] for f in feats]
            feats2 = [f[b:] for f in feats]
            i1, i2 = a, c
        flows = self._infer(feats1, feats2, i1, i2)
        if not all_scales:
            flows = flows[:1]
        return [resize_flow(f, (h, w)) for f in flows]

    def forward(self, img1: torch.Tensor, img2: torch.Tensor,
                all_scales: bool = False) -> torch.Tensor | list[torch.Tensor]:
        """Flow from ``img1`` to ``img2``.

        Args:
            img1: (B,3,H,W) first image, [0,1].
            img2: (B,3,H,W) second image.
            all_scales: return every scale (finest first) instead of only the finest.

        Returns:
            (B,2,H,W) flow img1→img2 in input pixels, or a list of ``num_scales`` such tensors.
        """
        flows = self._run(img1, img2, pairs_swapped=False, all_scales=all_scales)
        return flows if all_scales else flows[0]

    def forward_backward(self, img1: torch.Tensor, img2: torch.Tensor, all_scales: bool = False
                         ) -> tuple[torch.Tensor, torch.Tensor] | tuple[list[torch.Tensor], list[torch.Tensor]]:
        """Forward (1→2) and backward (2→1) flow in one batched pass of 2B pairs (shared features).

        Args:
            img1: (B,3,H,W) first image, [0,1].
            img2: (B,3,H,W) second image.
            all_scales: return lists of every scale (finest first).

        Returns:
            ``(flow_fwd, flow_bwd)``, each (B,2,H,W) in input pixels (or lists of them).
        """
        b = img1.shape[0]
        flows = self._run(img1, img2, pairs_swapped=True, all_scales=all_scales)
        fwd = [f[:b] for f in flows]
        bwd = [f[b:] for f in flows]
        return (fwd, bwd) if all_scales else (fwd[0], bwd[0])
