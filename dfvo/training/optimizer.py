"""The optimiser of every training run: Adam, with PyTorch's fused kernel where the device has one.

The fused kernel updates all parameters in one pass instead of one operation per tensor group: measured on the 2-core
Zen 4, one Adam step of DepthNet + PoseNet (27 M parameters) takes 17 ms fused against 56 ms with the default
multi-tensor path (``benchmarks/train_step.py`` times whole steps). Same algorithm and hyper-parameters; the last
bits of the updates may differ. Runs that clip gradients (the flow recipes: ``model.grad_clip_norm``) keep the
multi-tensor path only where a gradient scaler is in use (``16-mixed``: the fused kernel unscales internally, after
the clipping would have seen scaled gradients); elsewhere they clip with :func:`clip_gradients` before the fused step
(Lightning's bf16 plugin refuses to clip for any fused optimiser, scaler or not). The flow recipes' Adam step: 3.7 ms
single-tensor, 0.6 ms fused (FlowNet ``small``, 0.52 M parameters, one thread, Zen 5).
"""

from __future__ import annotations

from collections.abc import Iterable

import torch

__all__ = ["FUSED_DEVICES", "adam", "clip_gradients", "uses_grad_scaler"]

FUSED_DEVICES = ("cpu", "cuda")  # device types with a fused Adam kernel in torch >= 2.4


def adam(params: Iterable[torch.nn.Parameter], lr: float, device: torch.device | str,
         clipped: bool = False) -> torch.optim.Adam:
    """``torch.optim.Adam(params, lr)``, fused on :data:`FUSED_DEVICES` (the parameters' ``device``) unless
    ``clipped``: Lightning's precision plugin clips the run's gradients (its mixed-precision plugin refuses a fused
    optimiser, which would unscale a gradient scaler's gradients only after the clipping). The flow runs clip through
    it only with a scaler (:func:`uses_grad_scaler`); otherwise they call :func:`clip_gradients` themselves and keep
    the fused kernel."""
    return torch.optim.Adam(params, lr=lr, fused=torch.device(device).type in FUSED_DEVICES and not clipped)


def uses_grad_scaler(trainer: object | None) -> bool:
    """Whether ``trainer`` (a Lightning Trainer, or None) scales the loss's gradients (``16-mixed`` precision)."""
    plugin = getattr(trainer, "precision_plugin", None)
    return getattr(plugin, "scaler", None) is not None


def clip_gradients(params: Iterable[torch.nn.Parameter], value: float, algorithm: str = "norm") -> None:
    """Clip the gradients of ``params`` in place: their global 2-norm to ``value`` (``algorithm="norm"``) or each
    element to ``[-value, value]`` (``"value"``), as Lightning's ``clip_gradients`` does for unscaled gradients;
    ``algorithm`` may be Lightning's ``GradClipAlgorithmType``, a string enum equal to those names."""
    if algorithm == "norm":
        torch.nn.utils.clip_grad_norm_(params, value)
    elif algorithm == "value":
        torch.nn.utils.clip_grad_value_(params, value)
    else:
        raise ValueError(f"gradient clipping algorithm {algorithm!r}: expected 'norm' or 'value'")
