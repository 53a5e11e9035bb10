"""The parts of an inference run built from its typed config: the device, the flow and depth sources with the
flow refinement and the online finetuner (:func:`build_sources`), and the per-frame observers (TensorBoard, the Rerun
recording, the ROS 2 bag: :func:`build_observers`). Used by the batch run (:mod:`dfvo.inference.pipeline`), the live
run (:mod:`dfvo.inference.live`) and the Python API (:mod:`dfvo.inference.api`) alike.
"""

from __future__ import annotations

import errno
import logging
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dfvo.inference.config import InferConfig, ViewerKind
from dfvo.inference.loop import FrameRecord
from dfvo.inference.outputs import is_bag, remove_output, writing
from dfvo.inference.rerun_observer import RerunObserver
from dfvo.inference.tb_logging import TensorboardObserver
from dfvo.sources import NetworkFlow, build_depth_source, build_flow_source, check_sources
from dfvo.training.online_flow import OnlineFlowFinetuner

__all__ = ["resolve_device", "Sources", "build_sources", "build_observers", "BagObserver", "first_stamp"]

log = logging.getLogger("dfvo.infer")


def resolve_device(name: str) -> str:
    """``auto`` -> ``cuda`` when torch sees a CUDA device, else ``cpu``; other names as given.

    Raises:
        ValueError: a ``cuda`` device asked for where torch sees none (one line saying what to use instead).
    """
    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError(f"device={name}: CUDA is not available on this machine; use device=cpu or device=auto")
    return name


@dataclass
class Sources:
    """What turns frames into flows and depths: the sources, the flow refinement (None: none), the online
    finetuner (None: none) and what ``summary.json`` says about them (``extra``)."""

    flow: Any
    depth: Any
    refine: Any
    finetuner: Any
    extra: dict[str, Any]


def build_sources(icfg: InferConfig, world: Any, device: str) -> Sources:
    """The flow and depth sources of ``icfg`` (``world``: the synthetic world for oracle sources, else None), every
    missing checkpoint reported at once before any is loaded."""
    check_sources(icfg.flow, icfg.depth, world)
    flow_src = build_flow_source(icfg.flow, world, device)
    depth_src = build_depth_source(icfg.depth, world, device)
    refine = icfg.flow.refine if isinstance(flow_src, NetworkFlow) and icfg.flow.refine.iterations > 0 else None
    finetuner = None
    if icfg.online_finetune:
        if not isinstance(flow_src, NetworkFlow):
            raise ValueError(f"online_finetune=true needs flow=network (flow={flow_src.name} cannot be finetuned)")
        if flow_src.runtime != "torch":
            raise ValueError(f"online_finetune=true needs flow.runtime.kind=torch (flow.runtime.kind="
                             f"{flow_src.runtime} runs an exported copy of the network, which finetuning would not "
                             "update)")
        finetuner = OnlineFlowFinetuner(flow_src.model, icfg.online)
    extra = {"sources": {"flow": flow_src.name, "depth": depth_src.name,
                         "flow_checkpoint": str(getattr(flow_src, "checkpoint", "")) or None,
                         "depth_checkpoint": str(getattr(depth_src, "checkpoint", "")) or None,
                         "flow_refinement": None if refine is None else asdict(refine),
                         "flow_runtime": getattr(flow_src, "runtime", None),
                         "depth_runtime": getattr(depth_src, "runtime", None),
                         "flow_runtime_reason": getattr(flow_src, "runtime_reason", None),
                         "depth_runtime_reason": getattr(depth_src, "runtime_reason", None),
                         "depth_every": int(icfg.depth.every)},
             "online_finetune": finetuner is not None, "device": device}
    return Sources(flow_src, depth_src, refine, finetuner, extra)


def build_observers(cfg: InferConfig, out: Path, seq: Any) -> list[Any]:
    """The per-frame loggers the config asks for (TensorBoard, the Rerun recording)."""
    observers: list[Any] = []
    if cfg.viewer.kind == ViewerKind.rerun:
        hw = tuple(seq.image(0).shape[-2:])
        observers.append(RerunObserver(out / "run.rrd", seq.K, hw, gt_poses=seq.poses, spawn=cfg.viewer.spawn))
    if cfg.tensorboard.enabled:
        observers.append(TensorboardObserver(out / "tensorboard", cfg.tensorboard.every))
    if cfg.output.rosbag:
        observers.append(BagObserver(cfg, out, seq.poses, first_stamp(seq)))
    return observers


class BagObserver:
    """``output.rosbag=true``: every frame into the ROS 2 bag ``OUT/bag/`` (:class:`dfvo.io.rosbag.OdometryBagWriter`;
    frame 0 at once, at ``first_stamp``). A bag left in ``OUT/bag/`` by an earlier run is replaced."""

    def __init__(self, cfg: InferConfig, out: Path, ground_truth: np.ndarray | None, first_stamp: float | None) -> None:
        from dfvo.io.rosbag import OdometryBagWriter, import_rosbags  # deferred: rosbags is an optional extra

        import_rosbags()  # a missing extra fails before the old bag is removed
        self.path = out / "bag"
        if is_bag(self.path):
            log.info("output.rosbag: replacing the bag of an earlier run in %s", self.path)
            remove_output(self.path)
        with self._writing():
            self.writer = OdometryBagWriter(self.path, cfg.output.ros_world_frame, cfg.output.ros_camera_frame,
                                            ground_truth, str(cfg.output.rosbag_storage))
            self.writer.write(0, np.eye(4), None, first_stamp)

    def on_frame(self, record: FrameRecord) -> None:
        with self._writing():
            self.writer.write(record.index, record.result.T_w_cur.detach().cpu().double().numpy(),
                              record.result.covariance, record.timestamp)

    def close(self) -> None:
        with self._writing():
            self.writer.close()

    @contextmanager
    def _writing(self) -> Iterator[None]:
        """The bag's write errors as :class:`~dfvo.inference.outputs.OutputWriteError` naming the bag: sqlite3
        reports a full disk as ``sqlite3.OperationalError: database or disk is full``, not as an ``OSError``."""
        import sqlite3

        with writing(self.path):
            try:
                yield
            except sqlite3.Error as err:
                full = "full" in str(err)
                raise OSError(errno.ENOSPC if full else errno.EIO, f"{err} (sqlite3)") from err




def first_stamp(seq: Any) -> float | None:
    """Frame 0's timestamp of ``seq`` (None without timestamps)."""
    return None if seq.timestamps is None else float(seq.timestamps[0])
