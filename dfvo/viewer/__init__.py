"""Viewing a run: a Rerun recording (``OUT/run.rrd``) written frame by frame, and a reader for it.

Both need the optional Rerun SDK (``pip install "dfvo[viewer]"``); it is imported only when a recorder is made
or a recording is read, so ``import dfvo.viewer`` works without it.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "dfvo.viewer.rerun_recorder": ("ENTITIES", "MISSING_SDK_MESSAGE", "RerunRecorder", "TRACKER_CODES"),
    "dfvo.viewer.rrd_reader": ("RrdContents", "read_rrd"),
}
_WHERE = {name: module for module, names in _EXPORTS.items() for name in names}
__all__ = sorted(_WHERE)


def __getattr__(name: str) -> Any:
    if name not in _WHERE:
        raise AttributeError(f"module 'dfvo.viewer' has no attribute {name!r}")
    return getattr(importlib.import_module(_WHERE[name]), name)


def __dir__() -> list[str]:
    return __all__
