"""The Python API: DF-VO one frame at a time, for frames that arrive as a robot moves.

    import dfvo
    vo = dfvo.Odometry.from_config(["img_res.width=640"], fx=718.9, fy=718.9, cx=607.2, cy=185.2)
    for image, stamp in camera:                     # (H,W,3) uint8 RGB arrays, seconds
        r = vo.step(image, stamp)
        r.T_w_c, r.T_prev_cur, r.covariance, r.tracker, r.flags, r.reasons

Convention:
    - The pipeline is ``infer.py``'s: the same Hydra config tree and defaults (:func:`Odometry.from_config` composes
      ``dfvo/conf/infer/infer.yaml`` with the given overrides), the same sources, refinement and tracker
      (:class:`dfvo.inference.loop.FrameStepper`), so the poses equal ``infer.py``'s on the same frames.
    - Frames: numpy (H,W) or (H,W,3) RGB arrays (uint8, uint16, or float in [0,1]) — OpenCV gives BGR: convert with
      ``image[..., ::-1]`` — or torch tensors (3,H,W) / (1,3,H,W) float in [0,1] (uint8 is divided by 255).
    - Intrinsics are given once, in pixels of the frames as given (``K`` (3,3), or ``fx, fy, cx, cy``; optional
      OpenCV ``dist``); the frames are undistorted and resized to the working size of ``img_res`` (as ``infer.py``
      does: width 640 by default, the height from the aspect ratio) and ``K`` follows (:attr:`Odometry.K`).
    - A frame of another size than the first is resized to the first's size with a note logged once
      (``size_change="resize"``), or refused with a ``ValueError`` (``size_change="refuse"``).
    - Poses are float64 numpy arrays: ``T_w_c`` (4,4) maps points of the current camera into the first camera's
      frame (the world; x right, y down, z forward), ``T_prev_cur`` (4,4) the step from the previous frame.
      ``covariance`` (6,6) is that of the step's error ``[phi (rad), dt (m)]`` with ``R_true = exp([phi]) R`` and
      ``t_true = t + dt`` in the previous camera's axes (:mod:`dfvo.tracking.covariance`); frame 0 has zeros.
    - A frame with NaN or infinite pixels (a dropped camera buffer) is not tracked: its result repeats the previous
      step (``tracker="constant_motion"``, flag ``bad_frame``, the reason in ``reasons``) and the next frame is
      tracked against the last good one; ``StepResult.index`` counts every frame given.

Importing this module loads torch, kornia and Hydra; ``import dfvo`` alone does not (``dfvo.Odometry`` is imported on
first use).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from dfvo.data.image_folder import FramePrep
from dfvo.data.image_io import array_to_image
from dfvo.data.intrinsics_check import check_intrinsics
from dfvo.data.transforms import resize_image
from dfvo.geometry.camera import intrinsics_matrix
from dfvo.inference.assembly import build_sources, resolve_device
from dfvo.inference.config import InferConfig, compose_infer_config, typed
from dfvo.inference.frames import working_hw
from dfvo.inference.loop import FrameStepper
from dfvo.inference.timing import StageTimer
from dfvo.tracking import VisualOdometry
from dfvo.tracking.covariance import constant_motion_covariance
from dfvo.tracking.diagnostics import FrameDiagnostics, TrackerUsed

__all__ = ["Odometry", "StepResult", "SIZE_CHANGE"]

log = logging.getLogger("dfvo.api")
SIZE_CHANGE = ("resize", "refuse")


@dataclass(frozen=True)
class StepResult:
    """One frame's result (see the module docstring for frames and units).

    Attributes:
        index: the frame's number (0 for the first). timestamp: as given to :meth:`Odometry.step`.
        T_w_c: (4,4) the camera's pose in the world (the first camera). T_prev_cur: (4,4) the step.
        covariance: (6,6) of the step's error, order ``[rx, ry, rz, tx, ty, tz]`` (rad, m).
        tracker: ``init`` (frame 0), ``E`` (essential matrix + scale), ``PnP`` or ``constant_motion`` (no tracker
            gave a pose: the previous step repeated, with a large covariance).
        flags: what happened besides the normal path, among ``constant_motion``, ``bad_frame`` (NaN or infinite
            pixels: not tracked), ``selection_failed``, ``selection_relaxed`` (selected under a relaxed
            forward-backward bound, ``tracker.correspondence.relaxed_inconsistency``), ``pnp_failed``,
            ``gate_rejected``, ``scale_predicted`` (the scale filter's prediction was used), ``resized`` (a frame of
            another size than the first).
        reasons: the tracker's reasons for each fallback or flag (empty on a normal frame).
        diagnostics: everything the tracker measured (the fields of ``frames.csv``).
    """

    index: int
    timestamp: float | None
    T_w_c: np.ndarray
    T_prev_cur: np.ndarray
    covariance: np.ndarray
    tracker: str
    flags: tuple[str, ...] = ()
    reasons: tuple[str, ...] = ()
    diagnostics: FrameDiagnostics | None = field(default=None, repr=False)

    @property
    def ok(self) -> bool:
        """The pose was measured (``E`` or ``PnP``; also frame 0), not a constant-motion guess."""
        return self.tracker != TrackerUsed.constant_motion.value


class Odometry:
    """Streaming monocular visual odometry with ``infer.py``'s pipeline (see the module docstring).

    Args:
        cfg: ``infer.py``'s configuration (an :class:`~dfvo.inference.config.InferConfig` or its DictConfig;
            :meth:`from_config` composes one). Its ``data`` node is not read, except ``data.camera_height``.
        K: (3,3) intrinsics in pixels of the frames as given, or ``fx, fy, cx, cy``. dist: OpenCV distortion
            ``[k1, k2, p1, p2(, k3(, k4, k5, k6))]`` (None: none).
        size_change: ``resize`` or ``refuse`` a frame of another size than the first.

    Raises:
        ValueError: missing or implausible intrinsics, an oracle source (it needs the synthetic world), a bad setting.
        CheckpointError: a network checkpoint is missing (names the file).
    """

    def __init__(self, cfg: InferConfig | Any, K: Any = None, *, fx: float | None = None, fy: float | None = None,
                 cx: float | None = None, cy: float | None = None, dist: Sequence[float] | None = None,
                 size_change: str = "resize") -> None:

        self.cfg: InferConfig = cfg if isinstance(cfg, InferConfig) else typed(cfg)
        self._intrinsics = _intrinsics(K, fx, fy, cx, cy)
        self._dist = None if dist is None else [float(d) for d in dist]
        if size_change not in SIZE_CHANGE:
            raise ValueError(f"size_change={size_change!r}; expected one of {SIZE_CHANGE}")
        self.size_change = size_change
        if self.cfg.num_threads:
            torch.set_num_threads(int(self.cfg.num_threads))
        self.device = resolve_device(self.cfg.device)
        self.sources = build_sources(self.cfg, None, self.device)
        self.timer = StageTimer()
        self.vo = VisualOdometry(self.cfg.tracker, self.cfg.flow.refine.pyramid)
        self._stepper: Any = None
        self._prep: Any = None
        self.native_size: tuple[int, int] | None = None
        self._noted_resize = False
        self._skipped = 0  # frames given but not tracked (NaN pixels): StepResult.index counts them
        self._coasting = 0  # such frames since the last tracked one
        self.last_record: Any = None  # the last frame's FrameRecord (flows, depths, matches; None for frame 0)
        self.last_image: torch.Tensor | None = None  # the last frame at the working size (3,H,W)

    @classmethod
    def from_config(cls, overrides: Sequence[str] = (), K: Any = None, **kwargs: Any) -> Odometry:
        """Build the default pipeline of ``infer.py`` with command-line style ``overrides`` (``["flow=dis",
        "tracker.scale.camera_height=1.65"]``), composed by Hydra from the same config tree; ``K`` / ``fx, fy, cx,
        cy`` / ``dist`` / ``size_change`` as in the constructor."""
        return cls(compose_infer_config(list(overrides)), K, **kwargs)

    # ------------------------------------------------------------------------------------------ properties
    @property
    def K(self) -> torch.Tensor | None:
        """(3,3) intrinsics at the working size (None before the first frame)."""
        return None if self._prep is None else self._prep.K.clone()

    @property
    def image_size(self) -> tuple[int, int] | None:
        """The working (height, width) (None before the first frame)."""
        return None if self._prep is None else tuple(self._prep.image_size)

    def reset(self) -> None:
        """Start a new trajectory: the next frame is frame 0 (intrinsics and working size are kept)."""
        if self._stepper is not None:
            self._stepper.reset()
        self._skipped = self._coasting = 0

    # ------------------------------------------------------------------------------------------ frames
    def step(self, image: Any, timestamp: float | None = None) -> StepResult:
        """Track one frame (numpy array or tensor, see the module docstring) taken at ``timestamp`` seconds."""
        tensor, resized = self._prepare(image)
        unusable = ~torch.isfinite(tensor)
        if bool(unusable.any()):
            return self._coast(timestamp, float(unusable.float().mean()), resized)
        record = self._stepper.push(tensor)
        self._coasting = 0
        self.last_record, self.last_image = record, tensor
        if record is None:
            return StepResult(self._skipped, timestamp, np.eye(4), np.eye(4), np.zeros((6, 6)), TrackerUsed.init.value,
                              ("resized",) if resized else (), (),
                              FrameDiagnostics(frame=0, tracker=TrackerUsed.init))
        record.timestamp = timestamp
        return _result(record, timestamp, resized, self._skipped)

    def _coast(self, timestamp: float | None, fraction: float, resized: bool) -> StepResult:
        """The result of a frame with NaN or infinite pixels (a dropped camera buffer): not tracked, the previous
        step repeated from the last tracked frame (flag ``bad_frame``); the tracker's state is left as it was, so the
        next frame is tracked against the last good one."""
        index = self._stepper.index + 1 + self._skipped
        self._skipped += 1
        self._coasting += 1
        reason = (f"frame {index}: {fraction:.0%} of its pixels are NaN or infinite (a dropped camera buffer?); not "
                  "tracked, the previous step repeated")
        log.warning("%s; the next frame is tracked against the last good one", reason)
        flags = ("constant_motion", "bad_frame") + (("resized",) if resized else ())
        if self._stepper.prev is None:  # no tracked frame yet: the trajectory starts at the next good one
            return StepResult(index, timestamp, np.eye(4), np.eye(4), np.zeros((6, 6)),
                              TrackerUsed.constant_motion.value, flags, (reason,))
        vo = self.vo
        step = vo.last_motion.clone()
        cov = constant_motion_covariance(step, self.cfg.tracker.covariance).numpy()
        T_w_c = vo.T_w @ torch.linalg.matrix_power(step, self._coasting)  # the steps since the last tracked frame
        return StepResult(index, timestamp, T_w_c.double().numpy(), step.double().numpy(), cov,
                          TrackerUsed.constant_motion.value, flags, (reason,))

    def _prepare(self, image: Any) -> tuple[torch.Tensor, bool]:
        """(3,H,W) working-size float frame of ``image`` and whether it had to be resized to the first size."""

        native = _native_size(image)
        if self.native_size is None:
            self._start(native)
        resized = native != self.native_size
        if resized:
            if self.size_change == "refuse":
                raise ValueError(f"frame {self._stepper.index + 1} is {native[1]}x{native[0]}, the first was "
                                 f"{self.native_size[1]}x{self.native_size[0]} (size_change=refuse)")
            if not self._noted_resize:
                log.warning("frame %d is %dx%d, the first was %dx%d: frames of another size are resized to the "
                            "first's (noted once; the intrinsics are those of the first size)",
                            self._stepper.index + 1, native[1], native[0], self.native_size[1], self.native_size[0])
                self._noted_resize = True
        direct = self._prep.undistort is None and not resized
        if isinstance(image, torch.Tensor):
            t = image.detach()
            t = t[0] if t.dim() == 4 else t
            t = t.float() / 255.0 if t.dtype == torch.uint8 else t.float()
            if t.shape[0] == 1:
                t = t.expand(3, -1, -1)
            t = t.cpu()
        else:
            t = array_to_image(image, size=self._prep.image_size if direct else None)
            if direct:
                return t, False
        if resized:
            t = resize_image(t, *self.native_size)
        return self._prep(t), resized

    def _start(self, native: tuple[int, int]) -> None:
        """At the first frame: check the intrinsics against its size, fix the working size, build the stepper."""

        fx, fy, cx, cy, dist = check_intrinsics(*self._intrinsics, native[1], native[0], self._dist,
                                                source="Odometry intrinsics")
        K_native = intrinsics_matrix(fx, fy, cx, cy, dtype=torch.float64)[0]
        self._prep = FramePrep(K_native, native, working_hw(self.cfg.img_res, native), dist)
        self.native_size = native
        src = self.sources
        self._stepper = FrameStepper(src.flow, src.depth, self.vo, self._prep.K, refine=src.refine, timer=self.timer,
                                     device=self.device, finetuner=src.finetuner)


def _intrinsics(K: Any, fx: float | None, fy: float | None, cx: float | None, cy: float | None
                ) -> tuple[float, float, float, float]:
    if K is not None:
        if any(v is not None for v in (fx, fy, cx, cy)):
            raise ValueError("Odometry: give the intrinsics once, as K or as fx, fy, cx, cy (not both)")
        Km = np.asarray(K.detach().cpu() if isinstance(K, torch.Tensor) else K, dtype=np.float64)
        if Km.shape != (3, 3):
            raise ValueError(f"Odometry: K of shape {Km.shape}; expected (3,3) in pixels of the frames")
        return float(Km[0, 0]), float(Km[1, 1]), float(Km[0, 2]), float(Km[1, 2])
    if any(v is None for v in (fx, fy, cx, cy)):
        raise ValueError("Odometry needs the camera intrinsics: K=(3,3) or fx=, fy=, cx=, cy= in pixels of the frames")
    return float(fx), float(fy), float(cx), float(cy)


def _native_size(image: Any) -> tuple[int, int]:
    if isinstance(image, torch.Tensor):
        shape = tuple(image.shape)
        if not (len(shape) == 3 or (len(shape) == 4 and shape[0] == 1)) or shape[-3] not in (1, 3):
            raise ValueError(f"frame tensor of shape {shape}; expected (3,H,W) or (1,3,H,W)")
        return int(shape[-2]), int(shape[-1])
    shape = np.shape(image)
    if len(shape) not in (2, 3) or (len(shape) == 3 and shape[2] not in (1, 3)):
        raise ValueError(f"frame array of shape {shape}; expected (H,W) or (H,W,3) RGB")
    return int(shape[0]), int(shape[1])


def _result(record: Any, timestamp: float | None, resized: bool, skipped: int = 0) -> StepResult:
    res = record.result
    diag: FrameDiagnostics = res.diagnostics
    flags = [name for name, on in (("constant_motion", diag.constant_motion),
                                   ("selection_failed", diag.selection_failed),
                                   ("selection_relaxed", diag.selection_max_inconsistency is not None),
                                   ("pnp_failed", diag.pnp_failed),
                                   ("gate_rejected", diag.gate_rejected),
                                   ("scale_predicted", str(diag.scale_source or "").startswith("prediction")),
                                   ("resized", resized)) if on]
    reasons = tuple(r for r in (diag.fallback_reason or "").split("; ") if r)
    cov = res.covariance.detach().cpu().numpy() if res.covariance is not None else np.full((6, 6), np.nan)
    return StepResult(record.index + skipped, timestamp, res.T_w_cur.detach().cpu().double().numpy(),
                      res.T_prev_cur.detach().cpu().double().numpy(), cov,
                      diag.tracker.value if diag.tracker is not None else "none", tuple(flags), reasons, diag)
