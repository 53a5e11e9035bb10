"""``data=stream``: a live H.264/MPEG-TS stream served on loopback by the test itself (frames of the synthetic world),
tracked by ``infer.py`` as it arrives: frames in, poses out, dropped frames counted, outputs complete when the stream
ends, is cut or stalls; a growing file followed; bad sources in one line."""

from __future__ import annotations

import csv
import json
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from dfvo.synthetic import SyntheticWorld

av = pytest.importorskip("av", reason="data=stream needs PyAV (the video extra)")

REPO = Path(__file__).resolve().parents[2]
H, W = 96, 320
SMALL = [f"img_res.width={W}", "num_threads=1"]
needs_checkpoints = pytest.mark.skipif(not (REPO / "dfvo/checkpoints/flow.safetensors").is_file(),
                                       reason="no shipped checkpoints in dfvo/checkpoints")


@pytest.fixture(scope="module")
def frames() -> list[np.ndarray]:
    world = SyntheticWorld(seed=0, num_frames=12, height=H, width=W)
    return [(world.image(k).permute(1, 2, 0).numpy() * 255).round().astype(np.uint8) for k in range(12)]


@pytest.fixture(scope="module")
def intrinsics() -> list[str]:
    K = SyntheticWorld(seed=0, num_frames=2, height=H, width=W).intrinsics().double().numpy()
    return [f"data.fx={K[0, 0]:.9g}", f"data.fy={K[1, 1]:.9g}", f"data.cx={K[0, 2]:.9g}", f"data.cy={K[1, 2]:.9g}"]


def encode(sink: object, frames: list[np.ndarray], after_frame: object = None, period_s: float = 0.0) -> None:
    """H.264 (x264, zero latency) in MPEG-TS into the file object ``sink``; ``after_frame(k)`` runs after frame k
    is sent and returns False to stop there without an end (a cut)."""
    out = av.open(sink, "w", format="mpegts", options={"flush_packets": "1"})
    stream = out.add_stream("libx264", rate=10)
    stream.width, stream.height, stream.pix_fmt = W, H, "yuv420p"
    stream.options = {"tune": "zerolatency", "preset": "ultrafast", "crf": "12"}
    for k, img in enumerate(frames):
        frame = av.VideoFrame.from_ndarray(img, format="rgb24")
        frame.pts = k
        for packet in stream.encode(frame):
            out.mux(packet)
        sink.flush()
        if after_frame is not None and after_frame(k) is False:
            return
        time.sleep(period_s)
    for packet in stream.encode():
        out.mux(packet)
    out.close()


class LoopbackServer:
    """Serves ``frames`` to the first TCP client on 127.0.0.1 (``url``) from a thread: ``mode`` ``end`` (all, then a
    proper end), ``cut`` (the connection closed after ``at`` frames), ``stall`` (``at`` frames, then silence for
    ``stall_s`` seconds, then closed) or ``garbage`` (``at`` frames, possibly none, then random bytes, 4 KB every
    50 ms, for ``stall_s`` seconds, then closed); ``period_s`` between frames."""

    def __init__(self, frames: list[np.ndarray], mode: str = "end", at: int = 5, stall_s: float = 20.0,
                 period_s: float = 0.0) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(1)
        self.url = f"tcp://127.0.0.1:{self.sock.getsockname()[1]}"
        self.frames, self.mode, self.at, self.stall_s, self.period_s = frames, mode, at, stall_s, period_s
        self.sent = 0
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        self.sock.settimeout(120)
        conn, _ = self.sock.accept()
        sink = conn.makefile("wb")

        def after(k: int) -> bool:
            self.sent = k + 1
            if self.mode != "end" and k + 1 == self.at:
                if self.mode == "stall":
                    time.sleep(self.stall_s)
                elif self.mode == "garbage":
                    garbage()
                return False
            return True

        def garbage() -> None:
            rng, until = np.random.default_rng(0), time.monotonic() + self.stall_s
            while time.monotonic() < until:
                sink.write(rng.integers(0, 256, 4096, dtype=np.uint8).tobytes())
                sink.flush()
                time.sleep(0.05)

        try:
            if self.mode == "garbage" and self.at == 0:  # nothing but garbage
                garbage()
            else:
                encode(sink, self.frames, after, self.period_s)
        except OSError:  # the client went away first
            pass
        finally:
            try:
                sink.close()
                conn.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            conn.close()
            self.sock.close()


@pytest.fixture
def stream_infer(infer_cli, tmp_path: Path):
    """``infer.py data=stream ARGS`` (the ``infer_cli`` fixture) writing into ``tmp_path/out``: (process, out)."""
    out = tmp_path / "out"

    def run(*args: str, timeout: float = 600) -> tuple[subprocess.CompletedProcess, Path]:
        return infer_cli("data=stream", f"out_dir={out}", "progress=false", *SMALL, *args, check=False), out

    return run


def check_outputs(out: Path, name: str = "stream") -> tuple[dict, list[dict], np.ndarray]:
    """summary.json, frames.csv rows and the poses; one row and one pose per tracked frame, finite poses."""
    summary = json.loads((out / "summary.json").read_text())
    rows = list(csv.DictReader((out / "frames.csv").open()))
    poses = np.loadtxt(out / f"{name}.txt", ndmin=2)
    n = summary["stream"]["frames_tracked"]
    assert len(rows) == n == len(poses) == summary["frames_written"]
    assert np.isfinite(poses).all() and [int(r["frame"]) for r in rows] == list(range(n))
    assert all(r["tracker"] in ("E", "PnP", "constant_motion") for r in rows[1:])
    assert all(r["cov_tz_tz"] for r in rows[1:])  # every tracked frame carries its covariance
    assert (out / "trajectory.png").is_file()
    return summary, rows, poses


@needs_checkpoints
def test_realtime_stream_keeps_the_latest_frame_and_counts_the_dropped(frames, intrinsics,
                                                                       stream_infer) -> None:
    """12 frames sent at once while the networks are still loading: real-time mode tracks the latest frame each time
    and counts every frame it skipped, per frame (dropped_before) and in summary.json."""
    server = LoopbackServer(frames)
    proc, out = stream_infer(f"data.url={server.url}", *intrinsics)
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary, rows, _ = check_outputs(out)
    stream = summary["stream"]
    assert stream["frames_received"] == len(frames) and stream["ended_by"] == "end"
    assert stream["frames_dropped"] >= 1
    assert stream["frames_tracked"] + stream["frames_dropped"] == stream["frames_received"]
    assert sum(int(r["dropped_before"]) for r in rows) == stream["frames_dropped"]
    assert [int(r["stream_frame"]) for r in rows] == sorted(int(r["stream_frame"]) for r in rows)
    assert int(rows[-1]["stream_frame"]) == len(frames) - 1  # the latest frame is never dropped
    assert float(rows[1]["timestamp"]) > float(rows[0]["timestamp"])
    said = [ln for ln in (proc.stdout + proc.stderr).splitlines() if f"stream {server.url}: end;" in ln]
    assert len(said) == 1 and f"{stream['frames_dropped']} dropped" in said[0]


@needs_checkpoints
@pytest.mark.slow  # the reader's own test covers handing out every frame; this is the whole run
def test_every_frame_when_not_realtime_and_the_poses_follow_the_drive(frames, intrinsics,
                                                                      stream_infer) -> None:
    """``data.realtime=false``: every frame of the stream is tracked (none dropped), and the trajectory moves forward
    like the world's (the frames went through H.264, so the comparison is loose)."""
    server = LoopbackServer(frames)
    proc, out = stream_infer(f"data.url={server.url}", "data.realtime=false", "pose_format=tum", *intrinsics)
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary, rows, poses = check_outputs(out)
    assert summary["stream"]["frames_tracked"] == len(frames) and summary["stream"]["frames_dropped"] == 0
    assert np.allclose(poses[:, 0], np.arange(len(frames)) * 0.1, atol=1e-6)  # TUM time column: the stream's pts
    world = SyntheticWorld(seed=0, num_frames=12, height=H, width=W).poses().double().numpy()
    true_z = (np.linalg.inv(world[0]) @ world[-1])[2, 3]
    assert poses[-1, 3] == pytest.approx(true_z, rel=0.35)  # z forward: metres driven, within the networks' error


@needs_checkpoints
@pytest.mark.parametrize("mode", ["cut", "stall"])
def test_a_cut_or_stalled_stream_ends_with_one_line_and_complete_outputs(frames, intrinsics, tmp_path: Path,
                                                                         mode: str, stream_infer) -> None:
    """The server stops after 5 frames: closing the connection (cut) or going silent (stall, longer than
    ``data.timeout_s``). The run ends with exit status 0, one line saying how the source ended, and outputs for
    the 5 frames."""
    server = LoopbackServer(frames, mode=mode, at=5, stall_s=30.0)
    proc, out = stream_infer(f"data.url={server.url}", "data.realtime=false", "data.timeout_s=3", *intrinsics)
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary, rows, _ = check_outputs(out)
    stream = summary["stream"]
    assert stream["frames_tracked"] == 5 and stream["frames_received"] == 5
    assert stream["ended_by"] == ("end" if mode == "cut" else "stalled")
    lines = [ln for ln in (proc.stdout + proc.stderr).splitlines() if f"stream {server.url}" in ln]
    assert len(lines) == 1 and "5 frames tracked" in lines[0], proc.stdout[-2000:]
    assert (mode == "stall") == ("WARNING" in lines[0] and "no data for 3 s" in lines[0])
    assert "Traceback" not in proc.stderr and "exception being dropped" not in proc.stderr


@needs_checkpoints
@pytest.mark.slow
def test_a_growing_file_is_followed_until_it_stops_growing(frames, intrinsics, tmp_path: Path, stream_infer) -> None:
    """A recording still being written (MPEG-TS appended frame by frame): every frame written is tracked, and the
    run ends ``data.timeout_s`` after the file stopped growing."""
    path = tmp_path / "recording.ts"
    first = frames[:6]
    sink = path.open("wb")  # exists (empty) when the run starts, grows while infer.py reads it

    def write() -> None:
        time.sleep(1.0)
        encode(sink, first, period_s=0.3)
        sink.close()

    writer = threading.Thread(target=write, daemon=True)
    writer.start()
    proc, out = stream_infer(f"data.url={path}", "data.realtime=false", "data.timeout_s=4", *intrinsics)
    writer.join()
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary, _, _ = check_outputs(out)
    assert summary["stream"]["frames_tracked"] == len(first)


def test_a_source_that_cannot_be_opened_is_one_line(tmp_path: Path, stream_infer) -> None:
    """Nobody listening: infer.py ends with one line on stderr naming data.url (before loading any network); a
    missing camera device and a missing url are one line too."""
    from dfvo.data.image_io import DatasetError
    from dfvo.data.stream import StreamReader

    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    sock.close()  # nobody listens there
    proc, _ = stream_infer(f"data.url=tcp://127.0.0.1:{port}", "data.fx=100", "data.fy=100", "data.cx=160",
                        "data.cy=48", "data.timeout_s=2", timeout=120)
    assert proc.returncode == 1
    lines = [ln for ln in proc.stderr.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"dfvo-infer: error: data.url=tcp://127.0.0.1:{port}: cannot open "
                                                   "the stream"), proc.stderr
    with pytest.raises(DatasetError, match="^data.url=/dev/video77: no such camera device /dev/video77$"):
        StreamReader("/dev/video77").open()
    with pytest.raises(DatasetError, match="^data.url=77: no such camera device /dev/video77$"):
        StreamReader("77").open()
    with pytest.raises(ValueError, match="^data=stream needs data.url="):
        StreamReader(None)


def test_a_missing_extra_is_named_in_one_line(monkeypatch: pytest.MonkeyPatch) -> None:
    from dfvo.data.stream import STREAM_HINT, StreamReader

    monkeypatch.setitem(sys.modules, "av", None)  # import av raises ImportError
    with pytest.raises(ImportError, match=r"^data=stream needs PyAV: pip install \"dfvo\[video\]\"$"):
        StreamReader("tcp://127.0.0.1:1").open()
    assert "dfvo[video]" in STREAM_HINT


@pytest.mark.slow  # ~15 s: a healthy stream first, then garbage
def test_a_stream_that_turns_into_garbage_is_named_not_stalled() -> None:
    """A tcp:// stream of 60 good frames (0.1 s apart) that then sends random bytes without pause: the reader
    hands out the good frames and ends ``data.timeout_s`` after the last one as an ``error`` that says the bytes
    kept coming and did not decode (not as ``stalled``: data was arriving), long before the server stops."""
    from dfvo.data.stream import StreamReader

    rng = np.random.default_rng(1)
    imgs = [rng.integers(0, 255, (H, W, 3), dtype=np.uint8) for _ in range(70)]
    server = LoopbackServer(imgs, mode="garbage", at=60, stall_s=40.0, period_s=0.1)
    start = time.monotonic()
    reader = StreamReader(server.url, realtime=False, timeout_s=6.0)  # room for FFmpeg's probe on a busy CPU
    got = [f.index for f in reader]
    reader.close()
    took = time.monotonic() - start
    assert got == list(range(len(got))) and len(got) >= 55
    assert reader.ended_by == "error" and "none decoded as video" in reader.error, reader.error
    assert int(reader.error.split()[0]) >= 4096  # the bytes that arrived since the last frame are counted
    assert took < 6.0 + 6.0 + 10.0  # the frames, the timeout, slack: not the server's 40 s of garbage


@pytest.mark.slow  # ~12 s
def test_a_slow_consumer_of_a_healthy_stream_is_not_garbage() -> None:
    """The consumer stops for longer than ``data.timeout_s`` while the healthy stream goes on (its queue full):
    every frame is still handed out and the stream ends normally; the wait is not time without frames."""
    from dfvo.data.stream import StreamReader

    rng = np.random.default_rng(2)
    imgs = [rng.integers(0, 255, (H, W, 3), dtype=np.uint8) for _ in range(60)]
    server = LoopbackServer(imgs, mode="end", period_s=0.05)
    reader = StreamReader(server.url, realtime=False, timeout_s=3.0)
    got = []
    for f in reader:
        got.append(f.index)
        if f.index == 25:
            time.sleep(4.5)
    reader.close()
    assert got == list(range(60)) and reader.ended_by == "end", (len(got), reader.ended_by, reader.error)


def test_garbage_while_the_stream_opens_is_one_line() -> None:
    """A tcp:// source that sends only random bytes: opening it fails after data.timeout_s with one line that
    names the bytes (not 'no data'), and the socket is released."""
    from dfvo.data.image_io import DatasetError
    from dfvo.data.stream import StreamReader

    server = LoopbackServer([np.zeros((H, W, 3), np.uint8)], mode="garbage", at=0, stall_s=15.0)
    reader = StreamReader(server.url, realtime=False, timeout_s=2.0)
    with pytest.raises(DatasetError, match=r"cannot open the stream \(\d+ bytes arrived in the first 2 s and FFmpeg "
                                           r"found no complete video stream"):
        reader.open()
    assert reader._socket is not None and reader._socket.sock.fileno() == -1  # closed


def test_realtime_reader_drops_all_but_the_latest_frame() -> None:
    """The reader alone on a local file decoded faster than it is consumed: real time hands out the latest frame and
    counts the others; not real time hands out every frame."""
    import tempfile

    imgs = [np.full((H, W, 3), 10 * k, np.uint8) for k in range(10)]
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "clip.ts"
        with path.open("wb") as sink:
            encode(sink, imgs)
        from dfvo.data.stream import StreamReader

        every = StreamReader(str(path), realtime=False, timeout_s=1.0)
        got = [f.index for f in every]
        every.close()
        assert got == list(range(10)) and every.dropped == 0
        latest = StreamReader(str(path), realtime=True, timeout_s=1.0).start()
        time.sleep(1.5)  # everything decoded meanwhile
        first = next(iter(latest))
        latest.close()
        assert first.index == 9 and first.dropped_before == 9 and latest.dropped == 9
