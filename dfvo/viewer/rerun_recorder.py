"""A Rerun recording of an odometry run, written to ``run.rrd`` as frames are processed.

Every frame is flushed to the file before :meth:`RerunRecorder.log_frame` returns, so an interrupted run (Ctrl-C,
a killed job) leaves a file that Rerun opens with every frame logged so far (``rerun run.rrd``; such a file lacks
the closing footer, which :meth:`RerunRecorder.close` writes). ``spawn=True`` also streams to a live viewer where a
display exists; without one it warns once and writes the file only.

Entities (one timeline ``frame`` of frame indices; a second timeline ``time`` in seconds when timestamps are given):

=====================================  ================================================================================
``world``                              view coordinates RDF (static): x right, y down, z forward, as KITTI's camera
``world/ground_truth``                 line strip of the ground-truth camera centres (static, when given)
``world/path``                         line strip of the estimated camera centres up to this frame
``world/camera``                       ``Transform3D`` = ``T_w_c`` (float32) and ``pose_3x4``: the 12 numbers of the
                                       KITTI pose line (row-major top 3x4 of ``T_w_c``, float64)
``world/camera/image``                 ``Pinhole`` from K and the working size (static): the camera frustum
``world/camera/image/rgb``             the frame (JPEG, like flow and inconsistency, unless ``jpeg_quality=None``)
``world/camera/image/depth``           ``DepthImage`` in metres (float16, meter=1), back-projected in the 3-D view
``world/camera/image/correspondences`` the selected correspondences at their position in this frame, green =
                                       inlier, red = outlier (yellow when no inlier mask is given)
``world/camera/image/tracks``          segments from each correspondence's position in the previous frame
``world/points``                       triangulated points in world coordinates (as given: scaled)
``flow``                               forward flow, colour wheel (:func:`dfvo.vis.colour.flow_to_color`)
``inconsistency``                      forward-backward inconsistency: black 0 -> white >= ``inconsistency_max``
                                       pixels, blue = not finite (:func:`dfvo.vis.colour.scalar_to_color`)
``diagnostics/<key>``                  each numeric diagnostic as a scalar series (bools as 0/1); each string
                                       diagnostic as a text log; ``tracker`` also as ``diagnostics/tracker_code``
                                       (:data:`TRACKER_CODES`)
``log``                                one text line per frame (level WARN when the frame fell back)
=====================================  ================================================================================

Convention:
    Poses ``T_w_c`` (4,4) map camera points into the world (KITTI pose files). Image (3,H,W) float in [0,1]; flow
    (2,H,W) in pixels; inconsistency (1,H,W) in pixels; depth (1,H,W) in metres; points (N,2) in pixels of the
    working size (H,W); K (3,3) in pixels of that size. A leading batch axis of size 1 is accepted. Torch tensors
    and numpy arrays are both accepted.
"""

from __future__ import annotations

import logging
import math
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["RerunRecorder", "MISSING_SDK_MESSAGE", "TRACKER_CODES", "ENTITIES"]

log = logging.getLogger(__name__)

MISSING_SDK_MESSAGE = 'viewer=rerun needs the Rerun SDK: pip install "dfvo[viewer]"'
TRACKER_CODES = {"init": 0, "E": 1, "PnP": 2, "constant_motion": 3}
ENTITIES = ("world", "world/ground_truth", "world/path", "world/camera", "world/camera/image",
            "world/camera/image/rgb", "world/camera/image/depth", "world/camera/image/correspondences",
            "world/camera/image/tracks", "world/points", "flow", "inconsistency", "diagnostics", "log")
GREEN, RED, YELLOW = (40, 200, 40), (230, 40, 40), (240, 200, 0)
_warned_no_display = False


def _import_rerun() -> Any:
    try:
        import rerun as rr
    except ImportError:
        raise ImportError(MISSING_SDK_MESSAGE) from None
    return rr


def _has_display() -> bool:
    if sys.platform.startswith(("linux", "freebsd", "openbsd")):
        return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
    return True


def _array(x: Any, name: str, shape: tuple[int | None, ...]) -> np.ndarray:
    """``x`` (numpy or torch) as a numpy array of ``shape`` (None = any), a leading batch axis of 1 dropped."""
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    a = np.asarray(x)
    if a.ndim == len(shape) + 1 and a.shape[0] == 1:
        a = a[0]
    if a.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, a.shape)):
        want = "(" + ",".join("*" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"RerunRecorder: {name} has shape {tuple(a.shape)}; expected {want}")
    return a


def _pose(T: Any, name: str) -> np.ndarray:
    T = _array(T, name, (None, 4)).astype(np.float64)
    if T.shape[0] == 3:
        T = np.vstack([T, [0.0, 0.0, 0.0, 1.0]])
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise ValueError(f"RerunRecorder: {name} must be a finite (4,4) pose T_w_c, got shape {T.shape}")
    return T


def _to_uint8(rgb: np.ndarray) -> np.ndarray:
    """(3,H,W) float [0,1] -> (H,W,3) uint8."""
    a = rgb.astype(np.float32)
    if not np.isfinite(a).all():
        a = np.nan_to_num(a, copy=False)
    return (np.clip(a, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8).transpose(1, 2, 0)


def _scalar(v: Any) -> float | str | None:
    """A diagnostic as a float (bools as 0/1, numeric strings parsed), a non-empty string, or None (nothing to log:
    None, NaN, inf, "")."""
    if hasattr(v, "detach"):  # a torch tensor
        v = v.detach().cpu().numpy()
    if isinstance(v, np.ndarray | np.generic):
        v = v.item() if v.size == 1 else str(v.tolist())
    if isinstance(getattr(v, "value", None), str):  # an Enum such as TrackerUsed
        v = v.value
    if v is None:
        return None
    if isinstance(v, str):  # a frames.csv cell: numbers and True/False stay numbers, "" is nothing
        if v.strip().lower() in ("true", "false"):
            return float(v.strip().lower() == "true")
        try:
            f = float(v)
        except ValueError:
            return v.strip() or None
        return f if math.isfinite(f) else None
    if isinstance(v, bool | int | float | np.integer | np.floating | np.bool_):
        f = float(v)
        return f if math.isfinite(f) else None
    return str(v)


def default_blueprint(rrb: Any) -> Any:
    """3-D view (trajectory, frustum, depth points) beside the frame with its correspondences, flow, inconsistency,
    depth and the diagnostics (inliers, scale and tracker code; GRIC and every series in tabs)."""
    cam, d = "world/camera/image", "diagnostics"
    plots = rrb.Tabs(
        rrb.TimeSeriesView(origin=d, contents=["$origin/num_correspondences", "$origin/num_inliers"], name="inliers"),
        rrb.TimeSeriesView(origin=d, contents=["$origin/scale", "$origin/tracker_code"],
                           name="scale, tracker (0 init 1 E 2 PnP 3 const)"),
        rrb.TimeSeriesView(origin=d, contents=["$origin/gric_e", "$origin/gric_h"], name="GRIC"),
        rrb.TimeSeriesView(origin=d, name="all diagnostics"),
        rrb.TextLogView(origin="log", name="log"))
    right = rrb.Vertical(
        rrb.Spatial2DView(origin=cam, contents=["$origin", "$origin/rgb", "$origin/correspondences", "$origin/tracks"],
                          name="frame + correspondences (green inlier, red outlier)"),
        rrb.Horizontal(rrb.Spatial2DView(origin="flow", name="forward flow"),
                       rrb.Spatial2DView(origin="inconsistency", name="fb inconsistency")),
        rrb.Horizontal(rrb.Spatial2DView(origin=cam, contents=["$origin", "$origin/depth"], name="depth"), plots))
    return rrb.Blueprint(rrb.Horizontal(rrb.Spatial3DView(origin="world", name="trajectory"), right,
                                        column_shares=[2, 3]),
                         rrb.TimePanel(timeline="frame", play_state="following", state="collapsed"),
                         collapse_panels=True)


class RerunRecorder:
    """Write an odometry run to a Rerun recording, one flushed frame at a time.

    Args:
        path: the ``.rrd`` file to write (parent folders are created; an existing file is replaced).
        K: (3,3) intrinsics in pixels of the working size.
        image_hw: (H, W) working size of the images, depth and correspondences given to :meth:`log_frame`.
        spawn: also open the Rerun viewer and stream to it live (only where a display exists; otherwise one
            warning and the file only).
        gt_poses: (N,4,4) ground-truth ``T_w_c`` in the same world as the logged poses (no alignment is done),
            logged once as the line strip ``world/ground_truth``.
        images_every: log the image-like data (frame, depth, flow, inconsistency, correspondences) every this many
            frames (0: never); poses, points and diagnostics are logged every frame. A full-length KITTI run at
            640x192 takes ~0.3 MB a frame with images, mostly the depth.
        jpeg_quality: JPEG quality of the frame, flow and inconsistency images (None: raw, lossless).
        inconsistency_max: fb inconsistency (pixels) shown white; larger is clipped.
        flow_max: flow magnitude (pixels) shown fully saturated; None = each frame's maximum.
        application_id: Rerun application id (the viewer groups recordings by it).
        recording_name: shown in the viewer (e.g. the sequence name).

    Raises:
        ImportError: :data:`MISSING_SDK_MESSAGE` when the Rerun SDK is not installed.

    Example:
        >>> with RerunRecorder(out / "run.rrd", K, (H, W), gt_poses=gt) as rec:  # doctest: +SKIP
        ...     rec.log_frame(0, np.eye(4), image=img0)
        ...     rec.log_frame(1, T_w_c, image=img1, flow_fwd=flow, diagnostics=row)
    """

    def __init__(self, path: str | Path, K: Any, image_hw: tuple[int, int], spawn: bool = False,
                 gt_poses: Any | None = None, *, images_every: int = 1, jpeg_quality: int | None = 90,
                 inconsistency_max: float = 1.0, flow_max: float | None = None, application_id: str = "dfvo",
                 recording_name: str | None = None) -> None:
        global _warned_no_display
        rr = _import_rerun()
        import rerun.blueprint as rrb

        self._rr = rr
        self.path = Path(path)
        self.K = _array(K, "K", (3, 3)).astype(np.float64)
        if len(image_hw) != 2 or min(int(image_hw[0]), int(image_hw[1])) < 1:
            raise ValueError(f"RerunRecorder: image_hw={image_hw}; expected (H, W) in pixels")
        self.image_hw = (int(image_hw[0]), int(image_hw[1]))
        if images_every < 0:
            raise ValueError(f"RerunRecorder: images_every={images_every}; expected >= 0 (0 = no images)")
        self.images_every = int(images_every)
        self.jpeg_quality = jpeg_quality
        self.inconsistency_max = float(inconsistency_max)
        self.flow_max = flow_max
        self._positions: list[np.ndarray] = []
        self._closed = False
        self.frames_logged = 0

        self.path.parent.mkdir(parents=True, exist_ok=True)
        if self.path.exists():
            self.path.unlink()
        self.rec = rr.RecordingStream(application_id)
        blueprint = default_blueprint(rrb)
        self.spawned = False
        if spawn and not _has_display():
            if not _warned_no_display:
                log.warning("viewer.spawn=true but there is no display (DISPLAY/WAYLAND_DISPLAY unset): writing %s "
                            "only; open it later with `rerun %s`", self.path, self.path)
                _warned_no_display = True
        elif spawn:
            try:
                rr.spawn(connect=False, recording=self.rec, hide_welcome_screen=True)
                self.rec.set_sinks(rr.GrpcSink(), rr.FileSink(str(self.path)), default_blueprint=blueprint)
                self.spawned = True
            except Exception as e:  # the viewer is a convenience: never fail the run for it
                log.warning("could not start the Rerun viewer (%s): writing %s only", e, self.path)
        if not self.spawned:
            self.rec.save(str(self.path), default_blueprint=blueprint)
        if recording_name:
            self.rec.send_recording_name(str(recording_name))

        self.rec.log("world", rr.ViewCoordinates.RDF, static=True)
        H, W = self.image_hw
        self.rec.log("world/camera/image", rr.Pinhole(image_from_camera=self.K, resolution=[W, H],
                                                      camera_xyz=rr.ViewCoordinates.RDF), static=True)
        if gt_poses is not None:
            gt = _array(gt_poses, "gt_poses", (None, None, 4)).astype(np.float64)
            if gt.shape[1] not in (3, 4) or not np.isfinite(gt).all():
                raise ValueError(f"RerunRecorder: gt_poses has shape {gt.shape}; expected finite (N,4,4) T_w_c")
            self.rec.log("world/ground_truth", rr.LineStrips3D([gt[:, :3, 3]], colors=[(170, 170, 170)],
                                                               radii=rr.Radius.ui_points(1.5),
                                                               labels=["ground truth"]), static=True)
        self.rec.flush()

    # --------------------------------------------------------------------------------------------------- frames
    def log_frame(self, index: int, T_w_c: Any, image: Any | None = None, flow_fwd: Any | None = None,
                  inconsistency: Any | None = None, depth: Any | None = None, pts_prev: Any | None = None,
                  pts_cur: Any | None = None, inlier: Any | None = None, points_world: Any | None = None,
                  diagnostics: dict[str, Any] | None = None, timestamp_s: float | None = None) -> None:
        """Log frame ``index`` and flush it to the file.

        Args:
            index: frame index (the ``frame`` timeline).
            T_w_c: (4,4) (or (3,4)) camera-to-world pose of frame ``index``.
            image: (3,H,W) frame ``index`` in [0,1].
            flow_fwd: (2,h,w) forward flow in pixels (frame ``index-1`` -> ``index``: the pair that gave this pose).
            inconsistency: (1,h,w) forward-backward inconsistency of that flow, pixels.
            depth: (1,H,W) depth of frame ``index`` in metres (shown in its camera, back-projected in 3-D).
            pts_prev, pts_cur: (N,2) selected correspondences (x, y) in frames ``index-1`` and ``index``.
            inlier: (N,) bool inliers of the model that was used (None: not known).
            points_world: (M,3) triangulated points in world coordinates, in the trajectory's scale.
            diagnostics: per-frame values (a ``frames.csv`` row, as dicts of numbers or as the CSV's strings):
                numbers, bools and numeric strings become scalar series, other strings text logs; None, NaN, inf
                and "" are not logged for this frame.
            timestamp_s: optional time of the frame in seconds (the ``time`` timeline).
        """
        if self._closed:
            raise RuntimeError(f"RerunRecorder: log_frame({index}) after close() of {self.path}")
        rr, rec = self._rr, self.rec
        T = _pose(T_w_c, "T_w_c")
        rec.set_time("frame", sequence=int(index))
        if timestamp_s is not None:
            rec.set_time("time", duration=float(timestamp_s))
        rec.log("world/camera", rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]),
                rr.AnyValues(pose_3x4=T[:3, :4].reshape(-1)))
        self._positions.append(T[:3, 3].copy())
        rec.log("world/path", rr.LineStrips3D([np.asarray(self._positions)], colors=[(30, 110, 230)],
                                              radii=rr.Radius.ui_points(2.5)))
        if points_world is not None:
            pw = _array(points_world, "points_world", (None, 3)).astype(np.float32)
            pw = pw[np.isfinite(pw).all(axis=1)]
            rec.log("world/points", rr.Points3D(pw, colors=[(255, 140, 0)], radii=rr.Radius.ui_points(2.0)))
        if self.images_every and int(index) % self.images_every == 0:
            self._log_images(image, flow_fwd, inconsistency, depth, pts_prev, pts_cur, inlier)
        self._log_diagnostics(int(index), diagnostics or {})
        rec.flush()
        self.frames_logged += 1

    def _log_images(self, image: Any, flow_fwd: Any, inconsistency: Any, depth: Any, pts_prev: Any, pts_cur: Any,
                    inlier: Any) -> None:
        import torch  # deferred, with the colour maps that need it: reading a recording (rrd_reader) needs neither

        from dfvo.vis.colour import flow_to_color, scalar_to_color

        rr, rec = self._rr, self.rec
        H, W = self.image_hw
        if image is not None:
            rec.log("world/camera/image/rgb", self._image(_array(image, "image", (3, H, W))))
        if flow_fwd is not None:
            flow = torch.from_numpy(_array(flow_fwd, "flow_fwd", (2, None, None)).astype(np.float32))[None]
            rec.log("flow", self._image(flow_to_color(flow, self.flow_max)[0].numpy()))
        if inconsistency is not None:
            inc = torch.from_numpy(_array(inconsistency, "inconsistency", (1, None, None)).astype(np.float32))[None]
            rec.log("inconsistency", self._image(scalar_to_color(inc, vmax=self.inconsistency_max)[0].numpy()))
        if depth is not None:
            d = _array(depth, "depth", (1, H, W))[0].astype(np.float32)
            d = np.where(np.isfinite(d) & (d > 0), np.minimum(d, 65000.0), 0.0).astype(np.float16)
            rec.log("world/camera/image/depth", rr.DepthImage(d, meter=1.0))
        if pts_cur is not None:
            cur = _array(pts_cur, "pts_cur", (None, 2)).astype(np.float32)
            if inlier is not None:
                inl = _array(inlier, "inlier", (cur.shape[0],)).astype(bool)
                colors = np.where(inl[:, None], np.array(GREEN), np.array(RED)).astype(np.uint8)
            else:
                colors = np.tile(np.array(YELLOW, dtype=np.uint8), (cur.shape[0], 1))
            rec.log("world/camera/image/correspondences", rr.Points2D(cur, colors=colors,
                                                                      radii=rr.Radius.ui_points(2.5)))
            if pts_prev is not None:
                prev = _array(pts_prev, "pts_prev", (cur.shape[0], 2)).astype(np.float32)
                rec.log("world/camera/image/tracks", rr.LineStrips2D(np.stack([prev, cur], axis=1), colors=colors,
                                                                     radii=rr.Radius.ui_points(1.0)))

    def _image(self, chw: np.ndarray) -> Any:
        img = self._rr.Image(_to_uint8(chw))
        return img.compress(jpeg_quality=int(self.jpeg_quality)) if self.jpeg_quality else img

    def _log_diagnostics(self, index: int, diagnostics: dict[str, Any]) -> None:
        rr, rec = self._rr, self.rec
        parts = []
        for key, raw in diagnostics.items():
            if key == "frame":
                continue
            v = _scalar(raw)
            if v is None:
                continue
            entity = f"diagnostics/{rr.escape_entity_path_part(str(key))}"
            if isinstance(v, str):
                rec.log(entity, rr.TextLog(v))
                if key == "tracker" and v in TRACKER_CODES:
                    rec.log("diagnostics/tracker_code", rr.Scalars(float(TRACKER_CODES[v])))
            else:
                rec.log(entity, rr.Scalars(v))
            if key in ("tracker", "num_inliers", "scale", "fallback_reason"):
                parts.append(f"{key}={v:.4g}" if isinstance(v, float) else f"{key}={v}")
        fell_back = bool(_scalar(diagnostics.get("fallback_reason")) or _scalar(diagnostics.get("constant_motion"))
                         or _scalar(diagnostics.get("pnp_failed")))
        rec.log("log", rr.TextLog(f"frame {index}: " + (" ".join(parts) or "-"), level="WARN" if fell_back else "INFO"))

    # --------------------------------------------------------------------------------------------------- closing
    def close(self) -> None:
        """Flush and finish the file (writes Rerun's footer); a second call does nothing."""
        if self._closed:
            return
        self._closed = True
        try:
            self.rec.flush()
        finally:
            self.rec.disconnect()

    def __enter__(self) -> RerunRecorder:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
