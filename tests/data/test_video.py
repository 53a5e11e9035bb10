"""Video input: short videos written by the test from synthetic-world frames (lossless FFV1 in .mkv, H.264 with
B-frames in .mp4), decoded as a stream: frames equal the rendered ones, count, container timestamps (irregular),
step/range, seeking, the same frames as the PNG path, and the one-line messages."""

from __future__ import annotations

import sys
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from dfvo.data.image_folder import ImageFolder
from dfvo.data.image_io import DatasetError
from dfvo.data.intrinsics_check import IntrinsicsError
from dfvo.data.video import PYAV_HINT, VideoReader, open_video
from dfvo.synthetic import SyntheticWorld

av = pytest.importorskip("av", reason='PyAV not installed (pip install "dfvo[video]")')

N, H, W = 14, 64, 208
TIMES_MS = [0, 100, 250, 300, 420, 500, 600, 640, 700, 760, 800, 900, 1000, 1033]  # variable frame rate


@pytest.fixture(scope="module")
def clip(tmp_path_factory: pytest.TempPathFactory) -> dict:
    world = SyntheticWorld(seed=4, num_frames=N, height=H, width=W)
    frames = [(world.image(i).permute(1, 2, 0).numpy() * 255).round().astype(np.uint8) for i in range(N)]
    root = tmp_path_factory.mktemp("video")
    K = world.intrinsics()
    return {"frames": frames, "root": root, "K": [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])],
            "mkv": write_video(root / "clip.mkv", frames, "ffv1", "bgr0", {}),
            "mp4": write_video(root / "clip.mp4", frames, "libx264", "yuv444p", {"crf": "0", "bf": "2"}, gop=5)}


def write_video(path: Path, frames: list[np.ndarray], codec: str, pix_fmt: str, options: dict, gop: int = 12
                ) -> Path:
    with av.open(str(path), "w") as out:
        stream = out.add_stream(codec, rate=25)
        stream.width, stream.height, stream.pix_fmt, stream.options = W, H, pix_fmt, options
        stream.codec_context.time_base = Fraction(1, 1000)
        stream.codec_context.gop_size = gop
        for img, t in zip(frames, TIMES_MS):
            frame = av.VideoFrame.from_ndarray(img, format="rgb24")
            frame.pts, frame.time_base = t, Fraction(1, 1000)
            for packet in stream.encode(frame):
                out.mux(packet)
        for packet in stream.encode():
            out.mux(packet)
    return path


def as_tensor(img: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(img).permute(2, 0, 1).float() / 255


def test_lossless_frames_count_timestamps(clip: dict) -> None:
    seq = open_video(clip["mkv"], fx=clip["K"][0], fy=clip["K"][1], cx=clip["K"][2], cy=clip["K"][3])
    assert seq.name == "clip" and seq.length == N and seq.poses is None
    np.testing.assert_allclose(seq.timestamps, np.array(TIMES_MS) / 1000, atol=1e-9)
    for i in range(N):
        assert torch.allclose(seq.load(i), as_tensor(clip["frames"][i]), atol=1e-6), i
    assert torch.allclose(seq.K, torch.tensor([[clip["K"][0], 0, clip["K"][2]], [0, clip["K"][1], clip["K"][3]],
                                               [0, 0, 1.0]]))


def test_h264_with_b_frames(clip: dict) -> None:
    reader = VideoReader(clip["mp4"])
    assert len(reader) == N and reader.size == (H, W)
    np.testing.assert_allclose(reader.timestamps, np.array(TIMES_MS) / 1000, atol=1e-6)
    # crf 0 in 4:4:4 is lossless in YUV: only the RGB<->YUV rounding remains (a couple of levels)
    diffs = [np.abs(reader.read(i).astype(int) - clip["frames"][i]).max() for i in range(N)]
    assert max(diffs) <= 3, diffs
    # consecutive synthetic frames differ far more than that, so a frame off by one would show
    assert np.abs(clip["frames"][5].astype(int) - clip["frames"][6]).mean() > 5


def test_stream_decoding_and_seeks(clip: dict) -> None:
    reader = VideoReader(clip["mp4"], cache=3)
    decoded: list[int] = []
    original = reader._decode_next

    def counting() -> int:
        decoded.append(original())
        return decoded[-1]

    reader._decode_next = counting
    for i in range(N):  # in order: every frame decoded once
        reader.read(i)
    assert decoded == list(range(N)) and len(reader._cache) == 3
    decoded.clear()
    assert np.abs(reader.read(2).astype(int) - clip["frames"][2]).max() <= 3  # backwards: seek to keyframe 0
    assert decoded == [0, 1, 2]
    decoded.clear()
    assert np.abs(reader.read(12).astype(int) - clip["frames"][12]).max() <= 3  # within SEEK_AHEAD: decode forward
    assert decoded == list(range(3, 13))
    decoded.clear()
    assert np.abs(reader.read(7).astype(int) - clip["frames"][7]).max() <= 3  # back to the keyframe at 5 (gop 5)
    assert decoded == [5, 6, 7]
    with pytest.raises(IndexError, match="frame 14 out of range 0..13"):
        reader.read(N)
    reader.close()
    assert np.abs(reader.read(13).astype(int) - clip["frames"][13]).max() <= 3  # reopens after close


def test_step_range_and_resize_match_the_png_path(clip: dict, tmp_path: Path) -> None:
    fx, fy, cx, cy = clip["K"]
    seq = open_video(clip["mkv"], fx=fx, fy=fy, cx=cx, cy=cy, start=2, end=12, step=3, height=32, width=96)
    ids = [2, 5, 8, 11]
    assert seq.length == len(ids)
    np.testing.assert_allclose(seq.timestamps, np.array(TIMES_MS)[ids] / 1000, atol=1e-9)
    for i in ids:  # the same frames as PNG files through data=folder give the same tensors and K
        Image.fromarray(clip["frames"][i]).save(tmp_path / f"{i:03d}.png")
    folder = ImageFolder(tmp_path, fx, fy, cx, cy, height=32, width=96)
    assert torch.allclose(seq.K, folder.intrinsics)
    for k in range(len(ids)):
        assert torch.allclose(seq.load(k), folder[k]["image"], atol=1e-6)
    # with distortion, both paths undistort the same way
    dist = [-0.2, 0.05, 0.001, 0.0]
    und = open_video(clip["mkv"], fx=fx, fy=fy, cx=cx, cy=cy, dist=dist, start=2, end=4)
    ref = ImageFolder(tmp_path, fx, fy, cx, cy, dist=dist)[0]["image"]
    assert torch.allclose(und.load(0), ref, atol=1e-6) and not torch.allclose(und.load(0), as_tensor(clip["frames"][2]))


def test_messages(clip: dict, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    fx, fy, cx, cy = clip["K"]
    with pytest.raises(IntrinsicsError, match=r"^data.cx=3670 in video .*clip.mkv is outside the 208-px-wide image"):
        open_video(clip["mkv"], fx=fx, fy=fy, cx=3670, cy=cy)
    with pytest.raises(DatasetError, match=r"the range slice\(20, None, None\) selects 0"):
        open_video(clip["mkv"], fx=fx, fy=fy, cx=cx, cy=cy, start=20)
    (tmp_path / "notes.mp4").write_text("not a video")
    with pytest.raises(DatasetError, match=r"cannot open video .*notes.mp4: expected a video file"):
        open_video(tmp_path / "notes.mp4", fx=fx, fy=fy, cx=cx, cy=cy)
    with pytest.raises(FileNotFoundError, match="missing.mp4 does not exist"):
        open_video(tmp_path / "missing.mp4", fx=fx, fy=fy, cx=cx, cy=cy)
    monkeypatch.setitem(sys.modules, "av", None)  # as if PyAV were not installed
    with pytest.raises(ImportError) as err:
        open_video(clip["mkv"], fx=fx, fy=fy, cx=cx, cy=cy)
    assert str(err.value) == PYAV_HINT == 'data=video needs PyAV: pip install "dfvo[video]"'


def test_truncated_video_says_its_header_claims_more_frames(clip: dict, tmp_path: Path,
                                                            caplog: pytest.LogCaptureFixture) -> None:
    """Issue 42 (a container's claims are checked): an MP4 with its index at the front (faststart) cut at 60 %: its
    header still declares every frame, the reader names the file and both counts and uses the frames it holds,
    which decode to the rendered ones (the last, cut inside, may not); a whole file says nothing."""
    whole = tmp_path / "whole.mp4"
    with av.open(str(whole), "w", options={"movflags": "faststart"}) as out:
        stream = out.add_stream("ffv1", rate=10)
        stream.width, stream.height, stream.pix_fmt = W, H, "bgr0"
        for k, img in enumerate(clip["frames"]):
            frame = av.VideoFrame.from_ndarray(img, format="rgb24")
            frame.pts = k
            for packet in stream.encode(frame):
                out.mux(packet)
        for packet in stream.encode():
            out.mux(packet)
    cut = tmp_path / "cut.mp4"
    data = whole.read_bytes()
    cut.write_bytes(data[: int(0.6 * len(data))])
    with caplog.at_level("WARNING", "dfvo.data"):
        VideoReader(whole)
        assert not caplog.records
        reader = VideoReader(cut)
    assert 0 < reader.num_frames < N
    line = caplog.records[-1].getMessage()
    assert line == (f"video {cut}: its header declares {N} frames but {reader.num_frames} are in the file (truncated "
                    f"or damaged?); the {reader.num_frames} found are used")
    np.testing.assert_array_equal(reader.read(reader.num_frames - 2), clip["frames"][reader.num_frames - 2])
