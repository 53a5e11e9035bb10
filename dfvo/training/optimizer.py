"""The optimiser of every training run: Adam, with PyTorch's fused kernel where the device has one.

The fused kernel updates all parameters in one pass instead of one operation per tensor group: measured on the 2-core
Zen 4, one Adam step of DepthNet + PoseNet (27 M parameters) takes 17 ms fused against 56 ms with the default
multi-tensor path (``benchmarks/train_step.py`` times whole steps). Same algorithm and hyper-parameters; the last
bits of the updates may differ. Runs that clip gradients (the flow recipes: ``model.grad_clip_norm``) keep the
multi-tensor path, which Lightning's mixed-precision plugin can clip (the flow network's Adam step is ~5 ms).
"""

from __future__ import annotations

from collections.abc import Iterable

import torch

__all__ = ["FUSED_DEVICES", "adam"]

FUSED_DEVICES = ("cpu", "cuda")  # device types with a fused Adam kernel in torch >= 2.4


def adam(params: Iterable[torch.nn.Parameter], lr: float, device: torch.device | str,
         clipped: bool = False) -> torch.optim.Adam:
    """``torch.optim.Adam(params, lr)``, fused on :data:`FUSED_DEVICES` (the parameters' ``device``) unless the run
    clips gradients (``clipped``: Lightning's mixed-precision plugin refuses to clip for a fused optimiser, which
    unscales internally)."""
    return torch.optim.Adam(params, lr=lr, fused=torch.device(device).type in FUSED_DEVICES and not clipped)
