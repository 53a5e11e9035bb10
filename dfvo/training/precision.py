"""The arithmetic of a training run: ``trainer.precision=auto`` resolved from what the machine offers, and the loss
computations kept in float32 under mixed precision.

``auto`` (the default) is ``bf16-mixed`` — the networks' forward and backward under ``torch.autocast`` in bfloat16,
the weights, optimiser and losses in float32 — on a CUDA device with bf16 and on a CPU whose flags list bf16
instructions (``avx512_bf16`` or ``amx_bf16`` in ``/proc/cpuinfo``: Intel Cooper Lake / Sapphire Rapids and newer,
AMD Zen 4 and newer), and ``32-true`` elsewhere. Any of Lightning's values forces its choice
(``trainer.precision=32-true``). Measured on the 2-core Zen 4 (``benchmarks/train_step.py``, docs/training.md):
bf16 autocast is the larger half of the training speed-up; the losses stay float32 because SSIM's variances and the
reprojection's matrix products lose too much in bf16's 8-bit mantissa.
"""

from __future__ import annotations

from contextlib import AbstractContextManager

import torch

from dfvo.sources.runtime.engines import BF16_FLAGS, cpu_flags

__all__ = ["AUTO", "cpu_has_bf16", "resolve_precision", "float32_losses"]

AUTO = "auto"


def cpu_has_bf16() -> bool:
    """Whether this CPU has bf16 arithmetic instructions (``avx512_bf16`` or ``amx_bf16``; never assumed)."""
    return bool(cpu_flags() & set(BF16_FLAGS))


def resolve_precision(precision: str, accelerator: str) -> tuple[str, str]:
    """Lightning's ``precision`` for the setting ``precision`` on ``accelerator`` (``auto``, ``cpu``, ``gpu``,
    ``cuda``), and the reason, for the log.

    ``auto``: ``bf16-mixed`` where the device computes in bf16 (see the module docstring), else ``32-true``; any
    other value is returned as it is.
    """
    if precision != AUTO:
        return precision, f"trainer.precision={precision} (as set)"
    gpu = str(accelerator).lower() in ("gpu", "cuda") or (str(accelerator).lower() == "auto"
                                                          and torch.cuda.is_available())
    if gpu:
        if torch.cuda.is_available() and torch.cuda.is_bf16_supported():
            return "bf16-mixed", "trainer.precision=auto: the CUDA device computes in bf16"
        return "32-true", "trainer.precision=auto: the CUDA device has no bf16"
    if cpu_has_bf16():
        found = sorted(cpu_flags() & set(BF16_FLAGS))
        return "bf16-mixed", f"trainer.precision=auto: the CPU has bf16 instructions ({', '.join(found)})"
    return "32-true", (f"trainer.precision=auto: the CPU has no bf16 instructions ({' or '.join(BF16_FLAGS)} not in "
                       "/proc/cpuinfo's flags)")


def float32_losses(device: torch.device | str) -> AbstractContextManager:
    """A context in which autocast is off on ``device``'s type, so losses computed inside run in float32 (their
    inputs must be cast with ``.float()``); outside a mixed-precision run it changes nothing."""
    return torch.autocast(torch.device(device).type, enabled=False)
