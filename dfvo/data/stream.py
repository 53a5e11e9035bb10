"""Live sources read as frames arrive, with PyAV: a camera device, a network stream, a video file still being written.

Convention:
    - ``url``: ``/dev/videoN`` (or ``N``: ``/dev/videoN``; opened with FFmpeg's ``v4l2`` input on Linux), any URL
      FFmpeg reads (``rtsp://``, ``http://``, ``tcp://``, ``udp://``, ``srt://``), or a file path: a file is read on
      as it grows (FFmpeg's ``follow`` option) until no new data came for ``timeout_s`` seconds.
    - Frames are decoded in a background thread and handed out as :class:`StreamFrame` (8-bit RGB (H,W,3), in the
      order they arrived). ``realtime=True``: one slot holding the latest frame; a frame that arrives while the
      slot is still full replaces it and counts as dropped (``dropped_before`` of the next frame handed out, and
      :attr:`StreamReader.dropped`). ``realtime=False``: a short queue; when it is full the decoder waits (a network
      source then waits in its socket, a file is read at the consumer's pace), so every frame is handed out.
    - Timestamps: the frame's presentation time in seconds (``pts * time_base``) when the container has one, else
      the arrival time since the source was opened.
    - The source ends (:attr:`StreamReader.ended_by`) with ``end`` (the stream said so), ``stalled`` (no data for
      ``timeout_s``), ``error`` (the connection was cut, the data cannot be decoded; :attr:`StreamReader.error`
      says what) or ``closed`` (the consumer stopped). A ``tcp://`` source is read through a Python socket that
      counts its bytes (:class:`CountingSocket`), so garbage is told from silence: a source that goes on sending
      data none of which decodes as video ends as ``error`` naming that, not as ``stalled`` (FFmpeg's demuxer skips
      such bytes without a word, and a read timeout would then fire as for silence). Other network protocols are
      FFmpeg's own, without a byte count: garbage on them still ends as ``stalled``.
    - PyAV is an optional extra (``pip install "dfvo[video]"``); without it :func:`import_av` raises ``ImportError``
      naming it.
"""

from __future__ import annotations

import logging
import os
import queue
import re
import socket
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dfvo.data.image_io import DatasetError

__all__ = ["StreamFrame", "StreamReader", "CountingSocket", "NoData", "Undecodable", "resolve_url", "STREAM_HINT"]

log = logging.getLogger("dfvo.data")
STREAM_HINT = 'data=stream needs PyAV: pip install "dfvo[video]"'
QUEUE_FRAMES = 8  # frames buffered in non-realtime mode before the decoder waits
GARBAGE_BYTES = 4096  # read since the last frame without a new one: the source sends data that is not video
_END = object()


@dataclass
class StreamFrame:
    """One frame of a live source: ``image`` (H,W,3) uint8 RGB, ``timestamp`` seconds, ``index`` its number in the
    source (0-based, dropped frames counted), ``dropped_before`` frames dropped since the previous frame handed out."""

    image: np.ndarray
    timestamp: float
    index: int
    dropped_before: int = 0


def resolve_url(url: str, input_format: str | None) -> tuple[str, str | None, dict[str, str]]:
    """(what to open, input format, default options) of a ``data.url``: a bare number is ``/dev/videoN`` (v4l2), a
    ``/dev/video*`` path uses ``v4l2``, an existing file is followed as it grows."""
    url = str(url).strip()
    if re.fullmatch(r"\d+", url):
        url = f"/dev/video{url}"
    if url.startswith("/dev/video"):
        return url, input_format or "v4l2", {}
    if "://" not in url and Path(url).is_file():
        return url, input_format, {"follow": "1"}
    return url, input_format, {}


class StreamReader:
    """Frames of a live source, decoded in a background thread (see the module docstring).

    Args:
        url: the source (``data.url``). realtime: keep only the latest frame when the consumer falls behind.
        timeout_s: seconds to open the source and to wait for data before it counts as stalled.
        input_format: FFmpeg input format (None: from the url). options: FFmpeg options for opening it.

    Raises (on :meth:`open`):
        ImportError: PyAV missing. DatasetError: the source cannot be opened, or has no video stream (one line
        naming ``data.url``).
    """

    def __init__(self, url: str, *, realtime: bool = True, timeout_s: float = 10.0, input_format: str | None = None,
                 options: dict[str, str] | None = None) -> None:
        if not url:
            raise ValueError("data=stream needs data.url= (a camera device such as /dev/video0, a stream URL such as "
                             "rtsp://HOST/PATH or tcp://HOST:PORT, or a video file being written)")
        if not timeout_s > 0:
            raise ValueError(f"data.timeout_s={timeout_s}; expected seconds > 0")
        self.url, self.realtime, self.timeout_s = str(url), bool(realtime), float(timeout_s)
        self.source, self.input_format, defaults = resolve_url(self.url, input_format)
        self.options = {**defaults, **{str(k): str(v) for k, v in (options or {}).items()}}
        self.received = 0
        self.dropped = 0
        self.delivered = 0
        self.ended_by: str | None = None
        self.error: str | None = None
        self.size: tuple[int, int] | None = None
        self._container: Any = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._cond = threading.Condition()
        self._latest: StreamFrame | None = None
        self._pending_drops = 0
        self._queue: queue.Queue = queue.Queue(maxsize=QUEUE_FRAMES)
        self._finished = False
        self._socket: CountingSocket | None = None  # a tcp:// source, read through a byte counter

    # ------------------------------------------------------------------------------------------ lifecycle
    def open(self) -> StreamReader:
        """Open the source (blocking up to ``timeout_s``); decoding starts with :meth:`start`."""
        try:
            import av
        except ImportError:
            raise ImportError(STREAM_HINT) from None
        self._av = av
        if self.source.startswith("/dev/") and not os.path.exists(self.source):
            raise DatasetError(f"data.url={self.url}: no such camera device {self.source}")
        tcp = re.fullmatch(r"tcp://(?:\[([0-9A-Fa-f:.]+)\]|([^\[\]/?:]+)):(\d{1,5})/?", self.source)
        try:
            if tcp and int(tcp.group(3)) <= 65535 and not self.options:  # options (listen=1, ...): FFmpeg's own tcp
                self._socket = CountingSocket(tcp.group(1) or tcp.group(2), int(tcp.group(3)), self.timeout_s,
                                              self._stop)
                self._container = av.open(self._socket, format=self.input_format)
                self._socket.open_deadline = None
                if isinstance(self._socket.failure, Undecodable):  # data, but the probe was cut at the deadline
                    raise OSError(str(self._socket.failure))
            else:
                self._container = av.open(self.source, format=self.input_format, options=self.options,
                                          timeout=(self.timeout_s, self.timeout_s))
        except (av.error.FFmpegError, OSError) as err:
            reason = _reason(err)
            if self._container is not None:
                self._container.close()
                self._container = None
            if self._socket is not None:
                reason = _reason(self._socket.failure) if self._socket.failure is not None else reason
                self._socket.close()
            raise DatasetError(f"data.url={self.url}: cannot open the stream ({reason}); expected a camera "
                               "device, a stream URL FFmpeg reads, or a video file") from None
        if not self._container.streams.video:
            self._container.close()
            if self._socket is not None:
                self._socket.close()
            raise DatasetError(f"data.url={self.url}: the source has no video stream")
        stream = self._container.streams.video[0]  # no frame threading: it holds frames back (latency)
        self.size = (int(stream.codec_context.height), int(stream.codec_context.width))
        return self

    def start(self) -> StreamReader:
        """Start decoding in the background (opens first when needed)."""
        if self._container is None:
            self.open()
        self._t0 = time.monotonic()
        self._thread = threading.Thread(target=self._decode, name="dfvo-stream", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        """Stop decoding and release the source (frames not handed out yet are discarded)."""
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        while True:  # unblock a decoder waiting on the full queue
            try:
                self._queue.get_nowait()
            except queue.Empty:
                break
        if self._thread is not None:
            self._thread.join(timeout=self.timeout_s + 5.0)
        elif self._container is not None:  # opened, never started: the decoding thread would have closed it
            self._container.close()
            if self._socket is not None:
                self._socket.close()
        if self.ended_by is None:
            self.ended_by = "closed"

    def __enter__(self) -> StreamReader:
        return self.start()

    def __exit__(self, *exc: Any) -> None:
        self.close()

    # ------------------------------------------------------------------------------------------ decoding thread
    def _decode(self) -> None:
        av = self._av
        container = self._container
        stream = container.streams.video[0]
        try:
            for packet in container.demux(stream):  # the last (empty) packet flushes the decoder at the end
                if not self._emit(packet.decode()):
                    self.ended_by = "closed"
                    break
            else:
                failure = None if self._socket is None else self._socket.failure
                if self.ended_by is not None:  # the consumer ended it first (_stalled): its reason stands
                    pass
                elif isinstance(failure, NoData):
                    self.ended_by = "closed" if self._stop.is_set() else "stalled"
                    self.error = None if self._stop.is_set() else str(failure)
                elif isinstance(failure, Undecodable):
                    self.ended_by, self.error = "error", str(failure)
                elif failure is not None:
                    self.ended_by, self.error = "error", _reason(failure)
                else:
                    self.ended_by = "end"
        except av.error.ExitError:  # the interrupt callback of PyAV's timeout
            self.ended_by = "stalled"
            self.error = f"no data for {self.timeout_s:g} s"
            self._flush(stream)
        except av.error.FFmpegError as err:
            self.ended_by = "error"
            self.error = _reason(err)
            self._flush(stream)
        except Exception as err:  # noqa: BLE001 - the thread must always hand the end to the consumer
            self.ended_by = "error"
            self.error = f"{type(err).__name__}: {err}"
        finally:
            try:
                container.close()
            except Exception:  # noqa: BLE001
                pass
            if self._socket is not None:
                self._socket.close()
            self._finish()

    def _emit(self, decoded: Any) -> bool:
        """Hand out decoded frames; False once the consumer has stopped."""
        for frame in decoded:
            if self._stop.is_set():
                return False
            stamp = frame.time if frame.time is not None else time.monotonic() - self._t0
            item = StreamFrame(frame.to_ndarray(format="rgb24"), float(stamp), self.received)
            self.received += 1
            self._deliver(item)
            if self._socket is not None:  # after the hand-over: a slow consumer's wait is not time without frames
                self._socket.mark()
        return not self._stop.is_set()

    def _flush(self, stream: Any) -> None:
        """The frames still inside the decoder when the data stopped coming."""
        try:
            self._emit(stream.codec_context.decode(None))
        except Exception:  # noqa: BLE001 - a decoder that cannot flush keeps what it had
            pass

    def _deliver(self, item: StreamFrame) -> None:
        if self.realtime:
            with self._cond:
                if self._latest is not None:
                    self.dropped += 1
                    self._pending_drops += 1
                self._latest = item
                self._cond.notify_all()
            return
        while not self._stop.is_set():
            try:
                self._queue.put(item, timeout=0.1)
                return
            except queue.Full:
                continue

    def _finish(self) -> None:
        with self._cond:
            self._finished = True
            self._cond.notify_all()
        if not self.realtime:
            while not self._stop.is_set():
                try:
                    self._queue.put(_END, timeout=0.1)
                    return
                except queue.Full:
                    continue

    # ------------------------------------------------------------------------------------------ consumer
    def __iter__(self) -> Iterator[StreamFrame]:
        """Frames in arrival order until the source ends (see :attr:`ended_by`); a consumer that waits more than
        ``2 * timeout_s`` for a frame ends it as ``stalled``."""
        if self._thread is None:
            self.start()
        wait = 2.0 * self.timeout_s
        while not self._stop.is_set():
            item = self._next_realtime(wait) if self.realtime else self._next_queued(wait)
            if item is None:
                return
            self.delivered += 1
            yield item

    def _next_realtime(self, wait: float) -> StreamFrame | None:
        with self._cond:
            deadline = time.monotonic() + wait
            while self._latest is None and not self._finished and not self._stop.is_set():
                left = deadline - time.monotonic()
                if left <= 0:
                    self._stalled()
                    return None
                self._cond.wait(timeout=left)
            item = self._latest
            if item is None:
                return None
            item.dropped_before, self._pending_drops, self._latest = self._pending_drops, 0, None
            return item

    def _next_queued(self, wait: float) -> StreamFrame | None:
        try:
            item = self._queue.get(timeout=wait)
        except queue.Empty:
            self._stalled()
            return None
        return None if item is _END else item

    def _stalled(self) -> None:
        if self.ended_by is None:
            garbage = self.undecodable()
            self.ended_by = "error" if garbage else "stalled"
            self.error = garbage or f"no frame for {2.0 * self.timeout_s:g} s"
        self._stop.set()

    def undecodable(self) -> str | None:
        """Why no frame came although the source kept sending, on one line (a ``tcp://`` source that sent
        ``GARBAGE_BYTES`` or more since its last frame); None otherwise."""
        return None if self._socket is None else self._socket.undecodable()

    def stats(self) -> dict[str, Any]:
        """What ``summary.json`` reports: frames received, handed out and dropped, and how the source ended."""
        return {"url": self.url, "realtime": self.realtime, "frames_received": self.received,
                "frames_delivered": self.delivered, "frames_dropped": self.dropped, "ended_by": self.ended_by,
                "error": self.error}


class NoData(OSError):
    """No byte arrived on a :class:`CountingSocket` for its timeout (or the reader was closed)."""


class Undecodable(OSError):
    """Bytes kept arriving on a :class:`CountingSocket` but no frame was decoded from them for its timeout."""


class CountingSocket:
    """A connected TCP socket as the read-only, non-seekable file PyAV reads a ``tcp://`` source from.

    ``read(n)`` returns what arrived and counts it in ``bytes``. It ends the stream (b"", and ``failure`` says why:
    :class:`NoData` or :class:`Undecodable`) when nothing arrived for ``timeout_s`` (or ``stop`` is set), or when
    ``GARBAGE_BYTES`` or more arrived since the last :meth:`mark` (a decoded frame; not before the first one: a
    stream joined mid-GOP may take seconds to its first keyframe) and ``timeout_s`` has passed.
    It never raises into PyAV (whose read callback would print every exception after the first one).
    """

    def __init__(self, host: str, port: int, timeout_s: float, stop: threading.Event | None = None) -> None:
        self.sock = socket.create_connection((host, port), timeout=timeout_s)
        self.timeout_s = float(timeout_s)
        self.stop = stop
        self.bytes = 0
        self.failure: OSError | None = None
        # armed by the first decoded frame: before it, a stream may take a while to reach a keyframe
        self._mark_bytes: int | None = None
        self._mark_time = time.monotonic()
        # while PyAV opens the source (probes its format), it gives up after timeout_s whatever arrives, as
        # FFmpeg's own open timeout does; None once opened
        self.open_deadline: float | None = self._mark_time + self.timeout_s

    def mark(self) -> None:
        """A frame was decoded: the bytes and time from which :class:`Undecodable` counts."""
        self._mark_bytes, self._mark_time = self.bytes, time.monotonic()

    def undecodable(self) -> str | None:
        """One line when ``GARBAGE_BYTES`` or more arrived since the last mark, else None (also before the first)."""
        since = None if self._mark_bytes is None else self.bytes - self._mark_bytes
        if since is None or since < GARBAGE_BYTES:
            return None
        return (f"{since} bytes arrived in the {time.monotonic() - self._mark_time:.0f} s since the last frame and "
                "none decoded as video: the source sends data that is not its video stream (corrupt, or another "
                "format)")

    def readable(self) -> bool:
        return True

    def read(self, n: int = -1) -> bytes:
        if self.failure is not None:
            return b""
        if self.stop is not None and self.stop.is_set():
            self.failure = NoData("closed")
            return b""
        garbage = self.undecodable() if time.monotonic() - self._mark_time > self.timeout_s else None
        if garbage:
            self.failure = Undecodable(garbage)
            return b""
        if self.open_deadline is not None and time.monotonic() > self.open_deadline:
            self.failure = (Undecodable(f"{self.bytes} bytes arrived in the first {self.timeout_s:g} s and FFmpeg "
                                        "found no complete video stream in them: data that is not video (corrupt, or "
                                        "another format), or a stream slower to start than data.timeout_s")
                            if self.bytes >= GARBAGE_BYTES
                            else NoData(f"no data for {self.timeout_s:g} s"))
            return b""
        try:
            data = self.sock.recv(n if n > 0 else 65536)
        except TimeoutError:
            self.failure = NoData(f"no data for {self.timeout_s:g} s")
            return b""
        except OSError as err:  # reset by the peer, ...: the connection was cut
            self.failure = err
            return b""
        self.bytes += len(data)
        return data

    def close(self) -> None:
        try:
            self.sock.close()
        except OSError:
            pass


def _reason(err: Exception) -> str:
    """FFmpeg's message of a PyAV error, on one line."""
    text = getattr(err, "strerror", None) or str(err)
    return " ".join(str(text).split())
