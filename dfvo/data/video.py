"""Video files (``.mp4``, ``.mkv``, ``.mov``, ...) as frame sequences, decoded as a stream with PyAV.

Convention:
    - Frames are decoded in presentation order and kept only in a small cache (``cache`` frames, 8-bit RGB), so
      memory does not grow with the video. Reading frames in order decodes each once; reading backwards, or far
      ahead, seeks to the keyframe before the frame and decodes forward from there.
    - Frame ``i`` is the ``i``-th frame in presentation order. The frame list and the timestamps come from one
      pass over the container's packets (no decoding): ``timestamps[i] = pts_i * time_base`` in seconds, as
      stored (the first need not be 0; variable frame rates are kept).
    - Intrinsics ``fx, fy, cx, cy`` (and optional OpenCV ``dist``) are in pixels of the stored frames, checked by
      :mod:`dfvo.data.intrinsics_check`; rotation metadata (phone videos) is not applied, frames are used as
      stored (a warning says so).
    - ``load(i)`` gives (3,H,W) float [0,1] RGB at the working size (undistorted first when ``dist`` is given).
    - PyAV is an optional extra: without it, :func:`open_video` raises ``ImportError`` with one line saying how
      to install it.
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dfvo.data.image_folder import FramePrep
from dfvo.data.image_io import DatasetError, require_file
from dfvo.data.intrinsics_check import check_intrinsics
from dfvo.data.sequence import FrameSequence
from dfvo.data.transforms import check_working_size
from dfvo.geometry.camera import intrinsics_matrix

__all__ = ["VideoReader", "VideoSequence", "open_video", "PYAV_HINT"]

log = logging.getLogger("dfvo.data")
PYAV_HINT = 'data=video needs PyAV: pip install "dfvo[video]"'
SEEK_AHEAD = 64  # decode forward rather than seek when the wanted frame is at most this many frames ahead


def import_av() -> Any:
    """The ``av`` module, or ``ImportError`` with :data:`PYAV_HINT`."""
    try:
        import av
    except ImportError:
        raise ImportError(PYAV_HINT) from None
    return av


class VideoReader:
    """Random access to the frames of a video's first video stream, decoding as a stream.

    Args:
        path: video file.
        cache: how many decoded frames to keep (the most recent ones).

    Attributes:
        path, num_frames, size (height, width) of the stored frames, timestamps (N,) float64 seconds, pts (N,)
        int64 in ``time_base`` units, time_base (fractions.Fraction), rotation (degrees of display rotation).

    Raises:
        ImportError: PyAV missing. DatasetNotFoundError: no such file. DatasetError: not a video, no video
        stream, packets without timestamps, a frame that cannot be decoded (on access).
    """

    def __init__(self, path: str | Path, cache: int = 8) -> None:
        self._av = import_av()
        self.path = require_file(path, "video")
        self.cache_size = max(2, int(cache))
        container = self._open_container()
        try:
            stream = container.streams.video[0]
            declared = int(stream.frames or 0)  # the header's frame count (0: not stated)
            self.time_base = stream.time_base
            self.size = (int(stream.codec_context.height), int(stream.codec_context.width))
            pts = []
            for packet in container.demux(stream):
                if packet.size == 0 or packet.is_discard:
                    continue  # the final flush packet; edit-list pre-roll the decoder drops
                if packet.pts is None:
                    raise DatasetError(f"video {self.path}: packets without timestamps (a raw elementary stream?); "
                                       "remux it into .mkv or .mp4 first (ffmpeg -i IN -c copy OUT.mkv)")
                pts.append(int(packet.pts))
        except self._av.error.FFmpegError as err:
            raise DatasetError(f"cannot read video {self.path}: {err}") from None
        finally:
            container.close()
        if not pts:
            raise DatasetError(f"video {self.path} holds no video frames")
        self.pts = np.unique(np.asarray(pts, dtype=np.int64))
        self.num_frames = len(self.pts)
        if declared and declared != len(pts):  # what the container says is checked before it is trusted
            log.warning("video %s: its header declares %d frames but %d are in the file (%s); the %d found are "
                        "used", self.path, declared, len(pts),
                        "truncated or damaged?" if len(pts) < declared else "an edited or damaged header?", len(pts))
        if len(pts) != self.num_frames:
            log.warning("video %s: %d frames share a timestamp with another; each timestamp is used once",
                        self.path, len(pts) - self.num_frames)
        self.timestamps = self.pts * float(self.time_base)
        self._index = {int(p): i for i, p in enumerate(self.pts)}
        self._cache: OrderedDict[int, np.ndarray] = OrderedDict()
        self._container: Any = None
        self._frames: Any = None
        self._next: int | None = None  # index of the frame the decoder yields next (None: unknown after a seek)
        self.rotation = 0
        self._rotation_checked = False

    def _open_container(self) -> Any:
        try:
            container = self._av.open(str(self.path))
        except self._av.error.FFmpegError as err:
            raise DatasetError(f"cannot open video {self.path}: expected a video file ({err})") from None
        if not container.streams.video:
            container.close()
            raise DatasetError(f"video {self.path} has no video stream")
        return container

    def _restart(self, index: int = 0) -> None:
        """Position the decoder at frame 0 (``index == 0``) or at the keyframe before frame ``index``."""
        if self._container is None:
            self._container = self._open_container()
            self._container.streams.video[0].thread_type = "AUTO"
        stream = self._container.streams.video[0]
        self._container.seek(int(self.pts[index]), stream=stream, backward=True, any_frame=False)
        self._frames = self._container.decode(stream)
        self._next = 0 if index == 0 else None

    def _decode_next(self) -> int:
        try:
            frame = next(self._frames)
        except StopIteration:
            raise DatasetError(f"video {self.path}: the stream ended before frame {self._next} of "
                               f"{self.num_frames} (frames that cannot be decoded?)") from None
        except self._av.error.FFmpegError as err:
            raise DatasetError(f"video {self.path}: cannot decode the frame after {self._next}: {err}") from None
        index = self._index.get(int(frame.pts)) if frame.pts is not None else None
        if index is None:
            if self._next is None:
                raise DatasetError(f"video {self.path}: decoded a frame with an unknown timestamp after a seek")
            index = self._next
        if not self._rotation_checked:
            self._rotation_checked = True
            self.rotation = int(getattr(frame, "rotation", 0) or 0)
            if self.rotation:
                log.warning("video %s has %d-degree rotation metadata; frames are used as stored (not rotated), "
                            "give intrinsics in pixels of the stored %dx%d frames", self.path, self.rotation,
                            self.size[1], self.size[0])
        self._next = index + 1
        self._cache[index] = frame.to_ndarray(format="rgb24")
        self._cache.move_to_end(index)
        while len(self._cache) > self.cache_size:
            self._cache.popitem(last=False)
        return index

    def __len__(self) -> int:
        return self.num_frames

    def read(self, index: int) -> np.ndarray:
        """Frame ``index`` as an (H,W,3) uint8 RGB array (cached; do not modify)."""
        if not 0 <= index < self.num_frames:
            raise IndexError(f"video {self.path}: frame {index} out of range 0..{self.num_frames - 1}")
        if index in self._cache:
            self._cache.move_to_end(index)
            return self._cache[index]
        if self._frames is None or self._next is None or not self._next <= index <= self._next + SEEK_AHEAD:
            self._restart(index)
        from_start = self._next == 0
        while True:
            got = self._decode_next()
            if got == index:
                return self._cache[index]
            if got > index:  # passed it: the seek landed late, or the decoder dropped the frame
                if from_start:
                    raise DatasetError(f"video {self.path}: the decoder skipped frame {index} "
                                       f"(t = {self.timestamps[index]:.3f} s)")
                self._restart(0)
                from_start = True

    def close(self) -> None:
        """Release the decoder (reading again reopens the file)."""
        if self._container is not None:
            self._container.close()
        self._container, self._frames, self._next = None, None, None


class VideoSequence:
    """A range of a video's frames at the working size, with checked intrinsics and optional undistortion.

    Args:
        path: video file.
        fx, fy, cx, cy: intrinsics in pixels of the stored frames; dist: optional OpenCV distortion (4, 5, 8).
        height, width: working size (both or neither; None: the stored size).
        frames: range of frame indices (presentation order), Python slice semantics (start, end, step).
        cache: decoded frames kept in memory.

    Attributes:
        name, reader (:class:`VideoReader`), frame_ids, timestamps (s), K (3,3) float32 at the working size.
    """

    def __init__(self, path: str | Path, fx: float, fy: float, cx: float, cy: float, dist: list[float] | None = None,
                 height: int | None = None, width: int | None = None, frames: slice = slice(None),
                 cache: int = 8) -> None:
        self.reader = VideoReader(path, cache)
        self.name = Path(path).stem
        h, w = self.reader.size
        fx, fy, cx, cy, dist = check_intrinsics(fx, fy, cx, cy, w, h, dist, source=f"video {self.reader.path}")
        self.frame_ids = np.arange(len(self.reader))[frames]
        if len(self.frame_ids) < 2:
            raise DatasetError(f"video {self.reader.path} has {len(self.reader)} frames; the range {frames} selects "
                               f"{len(self.frame_ids)}, expected at least 2")
        working = check_working_size(height, width, f"video {self.reader.path}")
        self.prep = FramePrep(intrinsics_matrix(fx, fy, cx, cy, dtype=torch.float64)[0], (h, w), working, dist)
        self.K = self.prep.K
        self.timestamps = self.reader.timestamps[self.frame_ids]

    def __len__(self) -> int:
        return len(self.frame_ids)

    def image(self, index: int) -> torch.Tensor:
        """(3,H,W) float [0,1] frame ``index`` of the range."""
        arr = self.reader.read(int(self.frame_ids[index]))
        return self.prep(torch.from_numpy(arr).permute(2, 0, 1).float().div_(255.0))


def open_video(path: str | Path, *, fx: float, fy: float, cx: float, cy: float, dist: list[float] | None = None,
               height: int | None = None, width: int | None = None, start: int | None = None,
               end: int | None = None, step: int | None = None, cache: int = 8) -> FrameSequence:
    """A video file as a :class:`~dfvo.inference.frames.FrameSequence` (no ground truth; see :class:`VideoSequence`).

    ``start, end, step`` index the frames in presentation order (Python slice semantics).
    """
    seq = VideoSequence(path, fx, fy, cx, cy, dist, height, width, slice(start, end, step), cache)
    return FrameSequence(seq.name, len(seq), seq.K.clone(), seq.image, None, None, seq.timestamps)
