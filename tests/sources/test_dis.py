"""flow=dis: OpenCV DIS as a flow source, checked against the synthetic world's exact flow."""

from __future__ import annotations

import sys

import numpy as np
import pytest
import torch

from dfvo.sources.dis import MISSING_OPENCV, DISFlow, _to_gray_uint8
from dfvo.synthetic import SyntheticWorld

cv2 = pytest.importorskip("cv2")


@pytest.fixture(scope="module")
def world() -> SyntheticWorld:
    return SyntheticWorld(seed=0, num_frames=6, height=192, width=640)


def test_dis_recovers_the_true_flow(world: SyntheticWorld) -> None:
    src = DISFlow("medium")
    prev = torch.stack([world.image(1), world.image(2)])
    cur = torch.stack([world.image(2), world.image(3)])
    fwd, bwd = src(prev, cur, indices=[1, 2])
    assert src.name == "dis" and fwd.shape == bwd.shape == (2, 2, 192, 640) and fwd.dtype == torch.float32
    for b, i in enumerate((1, 2)):
        for flow, (gt, valid) in ((fwd[b], world.flow(i, i + 1)), (bwd[b], world.flow(i + 1, i))):
            err = (flow - gt).norm(dim=0)[valid[0]]
            mag = gt.norm(dim=0)[valid[0]].mean()
            assert mag > 10  # a real motion (13-15 px mean here)
            assert err.median() < 0.5 and (err < 1).float().mean() > 0.65
            assert err.mean() < 0.35 * mag  # zero flow would score 1.0 * mag


def test_dis_is_opencv_dis_on_8bit_gray(world: SyntheticWorld) -> None:
    a, b = world.image(1)[None], world.image(2)[None]
    gray = _to_gray_uint8(a)[0]
    rgb8 = (a[0].permute(1, 2, 0).numpy() * 255).astype(np.float32)
    ref_gray = np.round(cv2.cvtColor(rgb8, cv2.COLOR_RGB2GRAY)).astype(np.int32)
    assert np.abs(ref_gray - gray.astype(np.int32)).max() <= 1
    for preset in ("ultrafast", "fast", "medium"):
        fwd, bwd = DISFlow(preset)(a, b)
        dis = cv2.DISOpticalFlow_create(getattr(cv2, f"DISOPTICAL_FLOW_PRESET_{preset.upper()}"))
        ref = dis.calc(gray, _to_gray_uint8(b)[0], None)
        assert np.allclose(fwd[0].permute(1, 2, 0).numpy(), ref, atol=1e-4)


def test_dis_errors(monkeypatch: pytest.MonkeyPatch) -> None:
    with pytest.raises(ValueError, match="flow.preset='slow'"):
        DISFlow("slow")
    src = DISFlow("ultrafast")
    with pytest.raises(Exception, match="differ in shape"):
        src(torch.rand(1, 3, 32, 40), torch.rand(1, 3, 32, 48))
    monkeypatch.setitem(sys.modules, "cv2", None)  # "import cv2" now raises ImportError
    with pytest.raises(ImportError) as info:
        DISFlow()
    assert str(info.value) == MISSING_OPENCV and "\n" not in str(info.value)
    assert 'pip install "dfvo[classical]"' in MISSING_OPENCV and ".[classical]" in MISSING_OPENCV
