"""Image decoding (PNG 8/16 bit, JPEG, gray, palette, alpha) and the errors for missing/broken files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from dfvo.data.image_io import DatasetError, DatasetNotFoundError, image_size, list_images, read_image


def _rgb(h: int = 37, w: int = 53) -> np.ndarray:
    rng = np.random.default_rng(0)
    return rng.integers(0, 256, size=(h, w, 3), dtype=np.uint8)


def test_png_rgb_roundtrip_exact(tmp_path: Path) -> None:
    arr = _rgb()
    Image.fromarray(arr).save(tmp_path / "a.png")
    img = read_image(tmp_path / "a.png")
    assert img.shape == (3, 37, 53) and img.dtype == torch.float32 and img.is_contiguous()
    expected = torch.from_numpy(arr).permute(2, 0, 1).double() / 255.0
    torch.testing.assert_close(img.double(), expected, atol=1e-7, rtol=0)


def test_gray_png_replicated_to_three_channels(tmp_path: Path) -> None:
    arr = _rgb()[..., 0]
    Image.fromarray(arr, mode="L").save(tmp_path / "g.png")
    img = read_image(tmp_path / "g.png")
    assert img.shape == (3, 37, 53)
    torch.testing.assert_close(img[0], torch.from_numpy(arr).float() / 255.0)
    assert torch.equal(img[0], img[1]) and torch.equal(img[0], img[2])


def test_16bit_png_scaled_by_65535(tmp_path: Path) -> None:
    arr = (np.arange(20 * 30, dtype=np.int64).reshape(20, 30) * 109).astype(np.uint16)  # up to 65291
    Image.fromarray(arr).save(tmp_path / "d.png")
    assert Image.open(tmp_path / "d.png").mode.startswith("I")
    img = read_image(tmp_path / "d.png")
    assert img.shape == (3, 20, 30)
    torch.testing.assert_close(img[1].double(), torch.from_numpy(arr.astype(np.float64)) / 65535.0, atol=1e-6,
                               rtol=0)
    assert img.max() > 0.99  # not clipped or read as 8 bit


def test_rgba_and_palette(tmp_path: Path) -> None:
    arr = _rgb()
    rgba = np.concatenate([arr, np.full(arr.shape[:2] + (1,), 17, np.uint8)], axis=-1)
    Image.fromarray(rgba, mode="RGBA").save(tmp_path / "a.png")
    torch.testing.assert_close(read_image(tmp_path / "a.png"), torch.from_numpy(arr).permute(2, 0, 1) / 255.0)
    pal = Image.fromarray(arr).convert("P")
    pal.save(tmp_path / "p.png")
    expected = torch.from_numpy(np.array(pal.convert("RGB"))).permute(2, 0, 1) / 255.0
    torch.testing.assert_close(read_image(tmp_path / "p.png"), expected)


def test_jpeg_close_to_source(tmp_path: Path) -> None:
    y, x = np.mgrid[0:64, 0:96]
    arr = np.stack([x * 2, y * 3, (x + y)], -1).astype(np.uint8)  # smooth: JPEG error small
    Image.fromarray(arr).save(tmp_path / "a.jpg", quality=95)
    img = read_image(tmp_path / "a.jpg")
    assert img.shape == (3, 64, 96)
    assert (img - torch.from_numpy(arr).permute(2, 0, 1) / 255.0).abs().mean() < 0.01


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(DatasetNotFoundError, match="nope.png"):
        read_image(tmp_path / "nope.png")
    with pytest.raises(FileNotFoundError):  # also a FileNotFoundError for generic handlers
        read_image(tmp_path / "nope.png")


def test_truncated_png_raises_naming_the_file(tmp_path: Path) -> None:
    Image.fromarray(_rgb(120, 160)).save(tmp_path / "full.png")
    data = (tmp_path / "full.png").read_bytes()
    (tmp_path / "cut.png").write_bytes(data[: len(data) // 2])
    with pytest.raises(DatasetError, match="cut.png"):
        read_image(tmp_path / "cut.png")


def test_truncated_jpeg_raises(tmp_path: Path) -> None:
    Image.fromarray(_rgb(120, 160)).save(tmp_path / "full.jpg")
    data = (tmp_path / "full.jpg").read_bytes()
    (tmp_path / "cut.jpg").write_bytes(data[: len(data) // 3])
    with pytest.raises(DatasetError, match="cut.jpg"):
        read_image(tmp_path / "cut.jpg")


def test_not_an_image_raises(tmp_path: Path) -> None:
    (tmp_path / "text.png").write_text("this is not a png")
    with pytest.raises(DatasetError, match="text.png"):
        read_image(tmp_path / "text.png")
    with pytest.raises(DatasetError, match="text.png"):
        image_size(tmp_path / "text.png")


def test_list_images_natural_order_and_errors(tmp_path: Path) -> None:
    for name in ["frame10.png", "frame2.png", "frame1.jpg", "notes.txt"]:
        (tmp_path / name).write_bytes(b"")
    assert [p.name for p in list_images(tmp_path)] == ["frame1.jpg", "frame2.png", "frame10.png"]
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "readme.txt").write_text("x")
    with pytest.raises(DatasetError, match="contains no images"):
        list_images(empty)
    with pytest.raises(DatasetNotFoundError, match="missing"):
        list_images(tmp_path / "missing")


def test_real_kitti_gray_png(kitti_odom_root: Path) -> None:
    path = kitti_odom_root / "sequences" / "06" / "image_0" / "000000.png"
    img = read_image(path)
    assert img.shape == (3, 370, 1226)
    ref = torch.from_numpy(np.asarray(Image.open(path), dtype=np.float32) / 255.0)
    torch.testing.assert_close(img[2], ref)
    assert image_size(path) == (370, 1226)


@pytest.mark.parametrize("gray", [False, True])
def test_read_with_size_equals_resize_of_full_read(tmp_path: Path, gray: bool) -> None:
    arr = _rgb(75, 124)[..., 0] if gray else _rgb(75, 124)
    Image.fromarray(arr).save(tmp_path / "a.png")
    full = read_image(tmp_path / "a.png")
    small = read_image(tmp_path / "a.png", size=(38, 64), expected_size=(75, 124))
    assert small.shape == (3, 38, 64) and small.is_contiguous()
    ref = torch.nn.functional.interpolate(full[None], size=(38, 64), mode="bilinear", align_corners=False,
                                          antialias=False)[0]
    torch.testing.assert_close(small, ref, atol=1e-6, rtol=0)
    assert torch.equal(read_image(tmp_path / "a.png", size=(75, 124)), full)  # same size: no resampling
    with pytest.raises(DatasetError, match=r"a.png is 75x124, expected 76x124"):
        read_image(tmp_path / "a.png", expected_size=(76, 124))


def test_float_frames_with_negative_strides_and_0_255_floats() -> None:
    """Issue 42: a float frame given as frame[..., ::-1] (BGR to RGB) is read like its copy; a float frame in 0-255
    is refused in one line instead of tracking nothing."""
    from dfvo.data.image_io import array_to_image

    rgb = np.random.default_rng(0).random((6, 8, 3), dtype=np.float32)
    bgr = np.ascontiguousarray(rgb[..., ::-1])
    assert torch.equal(array_to_image(bgr[..., ::-1]), array_to_image(rgb))
    scaled = rgb * 255
    scaled[0, 0, 0] = 255.0
    with pytest.raises(ValueError, match="values up to 255; expected \\[0,1\\]"):
        array_to_image(scaled)


def test_folder_with_a_frame_twice_or_a_broken_link_is_refused(tmp_path: Path) -> None:
    """Issue 42: every frame exported twice (000001.png and 000001.jpg) gave twice the poses; a dangling link was
    skipped silently and shifted every later pose. Both are refused in one line naming the files."""
    for i in range(3):
        Image.fromarray(np.zeros((4, 6, 3), np.uint8)).save(tmp_path / f"{i:06d}.png")
    assert [p.name for p in list_images(tmp_path)] == ["000000.png", "000001.png", "000002.png"]
    Image.fromarray(np.zeros((4, 6, 3), np.uint8)).save(tmp_path / "000001.jpg")
    with pytest.raises(DatasetError, match=r"1 frame name with more than one file \(e.g. 000001.jpg, 000001.png\)"):
        list_images(tmp_path)
    (tmp_path / "000001.jpg").unlink()
    (tmp_path / "000003.png").symlink_to(tmp_path / "gone.png")
    with pytest.raises(DatasetError, match=r"1 broken link \(000003.png\)"):
        list_images(tmp_path)


def test_12bit_data_in_16bit_png_read_as_12bit(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """Issue 42: a 16-bit PNG holding 12-bit sensor data (values up to 4095) was divided by 65535, nearly black, and
    tracked as "100 % constant motion" without a cause: it is read as 12-bit, noted once for its folder."""
    import dfvo.data.image_io as image_io

    image_io._NOTED.clear()
    arr = (np.arange(20 * 30, dtype=np.int64).reshape(20, 30) * 6 + 495).astype(np.uint16)  # 495..4089
    for name in ("a.png", "b.png"):
        Image.fromarray(arr).save(tmp_path / name)
    with caplog.at_level("WARNING", "dfvo.data"):
        a, b = read_image(tmp_path / "a.png"), read_image(tmp_path / "b.png")
    torch.testing.assert_close(a[0].double(), torch.from_numpy(arr.astype(np.float64)) / 4095.0, atol=1e-6, rtol=0)
    assert torch.equal(a, b) and a.max() > 0.99
    notes = [r.getMessage() for r in caplog.records]
    assert len(notes) == 1 and notes[0].startswith(f"{tmp_path / 'a.png'}: 16-bit image with values up to 4089: read "
                                                   "as 12-bit data")


def test_exif_orientation_is_named_and_frames_read_as_stored(tmp_path: Path,
                                                             caplog: pytest.LogCaptureFixture) -> None:
    """Issue 42: a frame whose EXIF orientation says "rotated 90 degrees" is read as stored (as videos are), and the
    cause is named once (it was only "100 % constant motion")."""
    import dfvo.data.image_io as image_io

    image_io._NOTED.clear()
    arr = _rgb(30, 40)
    exif = Image.Exif()
    exif[0x0112] = 6
    Image.fromarray(arr).save(tmp_path / "r.jpg", exif=exif, quality=100)
    Image.fromarray(arr).save(tmp_path / "plain.jpg", quality=100)
    with caplog.at_level("WARNING", "dfvo.data"):
        rotated = read_image(tmp_path / "r.jpg")
        plain = read_image(tmp_path / "plain.jpg")
    assert rotated.shape == (3, 30, 40) and torch.equal(rotated, plain)  # the stored pixels, not turned
    notes = [r.getMessage() for r in caplog.records]
    assert len(notes) == 1 and notes[0].startswith(f"{tmp_path / 'r.jpg'}: EXIF orientation 6 (rotated 90 degrees in "
                                                   "viewers): frames are read as stored")
