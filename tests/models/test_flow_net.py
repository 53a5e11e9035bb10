"""FlowNet: shapes at every scale, the batched forward-backward call, resizing to multiples of 32."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from dfvo.geometry.camera import resize_flow
from dfvo.models.flow_net import FlowNet, FlowNetConfig


@pytest.fixture(scope="module")
def net() -> FlowNet:
    torch.manual_seed(0)
    model = FlowNet("tiny").eval()
    # Non-zero heads so the outputs are not trivially zero.
    with torch.no_grad():
        for block in model.cascade:
            for head in (block.match, block.subpixel):
                head[-1].weight.normal_(0, 0.05)
    return model


@pytest.mark.parametrize("variant,levels,scales", [("default", 6, 5), ("small", 5, 4), ("tiny", 4, 3)])
def test_shapes_all_scales(variant: str, levels: int, scales: int) -> None:
    model = FlowNet(variant)
    assert len(model.config.channels) == levels and model.num_scales == scales
    a, b = torch.rand(2, 3, 64, 96), torch.rand(2, 3, 64, 96)
    with torch.no_grad():
        fwd, bwd = model.forward_backward(a, b, all_scales=True)
        feats = model.pyramid(a)
    assert len(fwd) == len(bwd) == scales
    assert all(f.shape == (2, 2, 64, 96) for f in fwd + bwd)
    h, w = 64, 96
    for lev, f in enumerate(feats, start=1):
        h, w = (h + 1) // 2, (w + 1) // 2  # stride-2 conv with padding 1: ceil(n / 2)
        assert f.shape == (2, model.config.channels[lev - 1], h, w)


def test_forward_backward_equals_two_calls(net: FlowNet) -> None:
    g = torch.Generator().manual_seed(1)
    a, b = torch.rand(2, 3, 64, 64, generator=g), torch.rand(2, 3, 64, 64, generator=g)
    with torch.no_grad():
        fwd, bwd = net.forward_backward(a, b)
        torch.testing.assert_close(fwd, net(a, b), atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(bwd, net(b, a), atol=1e-5, rtol=1e-5)
    assert fwd.abs().max() > 1e-4  # the heads were perturbed, the flow is not identically zero


def test_non_multiple_of_32_is_resized_and_rescaled(net: FlowNet, monkeypatch: pytest.MonkeyPatch) -> None:
    """A 50x70 input runs at 64x96 inside; the finest level flow (16x24, stride 4) is resized straight to 50x70
    with u scaled by 70/24 and v by 50/16."""
    g = torch.Generator().manual_seed(2)
    a, b = torch.rand(1, 3, 50, 70, generator=g), torch.rand(1, 3, 50, 70, generator=g)
    seen: dict[str, torch.Tensor] = {}
    original = net._infer

    def spy(feats1, feats2, img1, img2):
        seen["img1"], seen["img2"] = img1, img2
        seen["flows"] = original(feats1, feats2, img1, img2)
        return seen["flows"]

    monkeypatch.setattr(net, "_infer", spy)
    with torch.no_grad():
        out = net(a, b)
    torch.testing.assert_close(seen["img1"], F.interpolate(a, size=(64, 96), mode="bilinear", align_corners=False))
    torch.testing.assert_close(seen["img2"], F.interpolate(b, size=(64, 96), mode="bilinear", align_corners=False))
    level = seen["flows"][0]
    assert level.shape == (1, 2, 16, 24)
    expected = F.interpolate(level, size=(50, 70), mode="bilinear", align_corners=False)
    expected = expected * torch.tensor([70 / 24, 50 / 16]).view(1, 2, 1, 1)
    assert out.shape == (1, 2, 50, 70)
    torch.testing.assert_close(out, expected, atol=1e-6, rtol=1e-6)


def test_upsample_flow_rescales_vectors() -> None:
    """The network upsamples its flows with the package's one flow resize (vectors in the new pixel units)."""
    flow = torch.zeros(1, 2, 4, 8)
    flow[:, 0], flow[:, 1] = 1.5, -0.5
    up = resize_flow(flow, (16, 16))
    torch.testing.assert_close(up[:, 0], torch.full((1, 16, 16), 3.0))
    torch.testing.assert_close(up[:, 1], torch.full((1, 16, 16), -2.0))


def test_regularisation_keeps_constant_flow() -> None:
    """The regularisation is a convex combination of neighbouring flows: a constant flow stays constant."""
    model = FlowNet("tiny")
    block = model.cascade[-1]
    with torch.no_grad():
        block.reg_feat[-1].weight.normal_(0, 1.0)
        for head in (block.match, block.subpixel):
            head[-1].weight.zero_()
            head[-1].bias.zero_()
        c = model.config.channels[model.config.finest_level - 1]
        flow = torch.tensor([2.0, -1.0]).view(1, 2, 1, 1).expand(1, 2, 8, 8).contiguous()
        out = block(torch.randn(1, c, 8, 8), torch.randn(1, c, 8, 8), torch.rand(1, 3, 8, 8),
                    torch.rand(1, 3, 8, 8), flow)
    torch.testing.assert_close(out, flow, atol=1e-5, rtol=1e-5)


def test_bad_config_and_input_raise() -> None:
    with pytest.raises(ValueError, match="unknown variant"):
        FlowNet("huge")
    with pytest.raises(Exception, match="search_range"):
        FlowNet(FlowNetConfig(channels=(8, 8, 8), search_range=(1, 1, 1, 1)))
    with pytest.raises(Exception, match="same shape"):
        FlowNet("tiny")(torch.rand(1, 3, 32, 32), torch.rand(1, 3, 32, 64))
