"""dfvo: monocular visual odometry from learned depth and optical flow plus multi-view geometry (DF-VO of Zhan et al.,
rebuilt in PyTorch + Kornia).

Command-line tools: ``dfvo-infer`` (``python infer.py``), ``dfvo-train``, ``dfvo-eval`` (:mod:`dfvo.cli`). Python API:
:class:`dfvo.Odometry` (frames in one at a time, poses with covariances out; :mod:`dfvo.api`). The subpackages and the
layer order their imports follow are mapped in ``docs/architecture.md``.

``import dfvo`` stays light: ``Odometry`` and ``StepResult`` are imported from :mod:`dfvo.api` on first use (PEP 562
module ``__getattr__``), because that loads torch, kornia and Hydra (about a second and a few hundred MB), which a
script that only reads a ``dfvo.eval`` helper or the version does not need.
"""

from __future__ import annotations

from typing import Any

__version__ = "0.1.0"  # the one home of the version (pyproject.toml reads it)

__all__ = ["Odometry", "StepResult", "__version__"]

_LAZY = {"Odometry": "dfvo.api", "StepResult": "dfvo.api"}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'dfvo' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
