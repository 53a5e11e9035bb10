"""dfvo: monocular visual odometry from learned depth and optical flow plus multi-view geometry (DF-VO, rebuilt in
PyTorch + Kornia).

Command-line tools: ``dfvo-infer`` (``python infer.py``), ``dfvo-train``, ``dfvo-eval``. Python API:
:class:`dfvo.Odometry` (frames in one at a time, poses with covariances out; :mod:`dfvo.api`).

``import dfvo`` stays light: ``Odometry`` and ``StepResult`` are imported from :mod:`dfvo.api` on first use (PEP 562
module ``__getattr__``), because that loads torch, kornia and Hydra (about a second and a few hundred MB), which a
script that only reads a ``dfvo.eval`` helper or the version does not need.
"""

from __future__ import annotations

from importlib import metadata as _metadata
from typing import Any

try:
    __version__ = _metadata.version("dfvo")
except _metadata.PackageNotFoundError:  # a source tree that is not installed
    __version__ = "0.0.0+unknown"

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
