"""Read a ``.rrd`` recording back with Rerun's own reader (``rerun.chunk.RrdReader``) into plain Python values.

Used by tests and checks: which entities a recording holds, and per entity and component the values logged at each
frame of the ``frame`` timeline. Reads files whose writer was interrupted (no footer) as well.

Convention:
    Entity paths without the leading ``/`` (``world/camera``); component names as Rerun stores them in a chunk
    (``Transform3D:translation``, ``Scalars:scalars``, ``TextLog:text``; ``pose_3x4`` for the recorder's
    float64 KITTI pose line). A value is what was logged at one frame: a list with one item per instance.
"""

from __future__ import annotations

import warnings
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from dfvo.viewer.rerun_recorder import MISSING_SDK_MESSAGE

__all__ = ["RrdContents", "read_rrd"]

_INDEX_COLUMNS = ("frame", "log_time", "time")


@dataclass
class RrdContents:
    """What a recording holds.

    Attributes:
        entities: every entity path with data (static or on a timeline).
        static: ``static[entity][component]`` = value logged once (static).
        rows: ``rows[entity][component]`` = list of ``(frame, value)`` in file order, one per ``log`` call.
        application_id: the recording's application id.
    """

    entities: set[str] = field(default_factory=set)
    static: dict[str, dict[str, Any]] = field(default_factory=lambda: defaultdict(dict))
    rows: dict[str, dict[str, list[tuple[int, Any]]]] = field(
        default_factory=lambda: defaultdict(lambda: defaultdict(list)))
    application_id: str | None = None

    def frames(self, entity: str, component: str) -> list[int]:
        """Frame indices at which ``entity`` logged ``component`` (sorted, with repeats if logged twice)."""
        return sorted(f for f, _ in self.rows.get(entity, {}).get(component, []))

    def values(self, entity: str, component: str) -> dict[int, Any]:
        """``{frame: value}`` of ``component`` of ``entity`` (the last value if a frame was logged twice)."""
        return dict(self.rows.get(entity, {}).get(component, []))

    def poses(self) -> dict[int, np.ndarray]:
        """``{frame: (4,4) float64 T_w_c}`` from the recorder's ``world/camera`` ``pose_3x4`` values."""
        out = {}
        for frame, v in self.values("world/camera", "pose_3x4").items():
            T = np.eye(4)
            T[:3, :4] = np.asarray(v, dtype=np.float64).reshape(3, 4)
            out[frame] = T
        return out

    def transforms(self) -> dict[int, np.ndarray]:
        """``{frame: (4,4) T_w_c}`` rebuilt from ``world/camera``'s ``Transform3D`` (float32 in the file)."""
        trans = self.values("world/camera", "Transform3D:translation")
        mats = self.values("world/camera", "Transform3D:mat3x3")
        out = {}
        for frame, t in trans.items():
            T = np.eye(4)
            T[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
            # Rerun stores Mat3x3 column-major
            T[:3, :3] = np.asarray(mats[frame], dtype=np.float64).reshape(3, 3).T
            out[frame] = T
        return out

    def scalars(self, key: str) -> dict[int, float]:
        """``{frame: value}`` of the scalar series ``diagnostics/<key>``."""
        return {f: float(np.asarray(v).reshape(-1)[0]) for f, v in self.values(f"diagnostics/{key}",
                                                                                "Scalars:scalars").items()}

    def texts(self, entity: str) -> dict[int, str]:
        """``{frame: text}`` of a text log entity (e.g. ``diagnostics/tracker`` or ``log``)."""
        return {f: v[0] for f, v in self.values(entity, "TextLog:text").items()}


def read_rrd(path: str | Path) -> RrdContents:
    """Read every chunk of the first recording in ``path``.

    Raises:
        ImportError: :data:`~dfvo.viewer.rerun_recorder.MISSING_SDK_MESSAGE` without the Rerun SDK, or a line
            naming the version when the installed SDK has no ``rerun.chunk.RrdReader`` (tested with 0.41).
        FileNotFoundError: ``path`` does not exist.
    """
    path = Path(path)
    try:
        import rerun  # noqa: F401
    except ImportError:
        raise ImportError(MISSING_SDK_MESSAGE) from None
    try:
        from rerun.chunk import RrdReader
    except ImportError:
        import rerun

        raise ImportError(f"reading {path} needs rerun.chunk.RrdReader (rerun-sdk >= 0.41); installed: "
                          f"{rerun.__version__}") from None
    if not path.is_file():
        raise FileNotFoundError(f"no Rerun recording at {path}")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "no footer" of an interrupted file: stream() reads it all the same
        reader = RrdReader(str(path))
        stores = reader.recordings()
        chunks = reader.stream().to_chunks()
    out = RrdContents(application_id=stores[0].application_id if stores else None)
    for chunk in chunks:
        entity = str(chunk.entity_path).lstrip("/")
        if entity.startswith("__"):  # recording properties
            continue
        batch = chunk.to_record_batch()
        names = [n for n in batch.schema.names if not n.startswith("rerun.controls") and n not in _INDEX_COLUMNS]
        if not names:
            continue
        out.entities.add(entity)
        if chunk.is_static:
            for n in names:
                out.static[entity][n] = batch.column(n).to_pylist()[-1]
            continue
        if "frame" not in batch.schema.names:
            continue
        frames = batch.column("frame").to_pylist()
        for n in names:
            for frame, value in zip(frames, batch.column(n).to_pylist(), strict=True):
                if value is not None:
                    out.rows[entity][n].append((int(frame), value))
    return out
