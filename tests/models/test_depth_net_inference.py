"""Depth network inference path: equals the training forward's scale 0, cache invalidation, state dict unchanged."""

from __future__ import annotations

import hashlib

import pytest
import torch
from torch import nn

from dfvo.models.depth_net import DepthNet, disp_to_depth, fold_batch_norms


def _random_batch_norms(net: nn.Module, seed: int) -> nn.Module:
    """Give every batch norm non-trivial affine parameters and running statistics (the default init is ~identity)."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for m in net.modules():
            if isinstance(m, nn.BatchNorm2d):
                n = m.num_features
                m.weight.copy_(0.5 + torch.rand(n, generator=g))
                m.bias.copy_(0.1 * torch.randn(n, generator=g))
                m.running_mean.copy_(0.2 * torch.randn(n, generator=g))
                m.running_var.copy_(0.5 + 1.5 * torch.rand(n, generator=g))
    return net


def _net(seed: int = 0) -> DepthNet:
    torch.manual_seed(seed)
    return _random_batch_norms(DepthNet(init_depth=10.0), seed).eval()


def _image(seed: int = 1, b: int = 2, h: int = 64, w: int = 96) -> torch.Tensor:
    return torch.rand(b, 3, h, w, generator=torch.Generator().manual_seed(seed))


def test_inference_path_equals_training_forward_scale0() -> None:
    net, x = _net(), _image()
    with torch.no_grad():
        ref = net(x)[0]
        disp = net.disparity(x)
        depth = net.depth(x)
    assert disp.shape == ref.shape == (2, 1, 64, 96) and disp.is_contiguous()
    torch.testing.assert_close(disp, ref, atol=1e-5, rtol=0)
    torch.testing.assert_close(depth, disp_to_depth(ref, net.min_depth, net.max_depth), atol=1e-5, rtol=1e-5)
    # the fast path really ran: the cached inference copy exists and is channels_last without batch norms
    encoder, decoder = net._inference_modules()
    assert not any(isinstance(m, nn.BatchNorm2d) for m in encoder.modules())
    assert encoder.conv1.weight.is_contiguous(memory_format=torch.channels_last)
    assert decoder.up1[4].conv.weight.is_contiguous(memory_format=torch.channels_last)
    with torch.inference_mode():
        torch.testing.assert_close(net.depth(x), depth)


def test_inference_path_full_resolution_640x192() -> None:
    net, x = _net(3), _image(4, b=1, h=192, w=640)
    with torch.no_grad():
        torch.testing.assert_close(net.disparity(x), net(x)[0], atol=1e-5, rtol=0)


def test_state_dict_unchanged_by_inference_cache() -> None:
    net, x = _net(), _image()
    before = {k: v.shape for k, v in net.state_dict().items()}
    net.depth(x)
    assert {k: v.shape for k, v in net.state_dict().items()} == before
    # the layout of the trained checkpoints (keys and shapes of the original DepthNet)
    layout = repr([(k, tuple(v.shape)) for k, v in net.state_dict().items()]).encode()
    assert len(before) == 148 and sum(v.numel() for v in net.state_dict().values()) == 14_338_856
    assert hashlib.sha256(layout).hexdigest() == "140e3fb2e8df43c4d66f698ad21ecc64be055f8f623629f797fd50a0124a7cb7"
    # a checkpoint of the new code loads into a fresh net strictly, and gives the same depth
    other = DepthNet().eval()
    other.load_state_dict(net.state_dict())
    torch.testing.assert_close(other.depth(x), net.depth(x))


def test_inference_cache_follows_weight_changes() -> None:
    net, x = _net(0), _image()
    net.depth(x)
    cached = net._inference_cache
    net.depth(x)
    assert net._inference_cache is cached  # reused while the weights do not change
    # load_state_dict (in-place copy into the parameters and buffers)
    other = _net(5)
    net.load_state_dict(other.state_dict())
    torch.testing.assert_close(net.depth(x), disp_to_depth(other(x)[0].detach()), atol=1e-5, rtol=1e-5)
    # in-place change of a batch-norm buffer
    with torch.no_grad():
        net.encoder.layer2[0].bn1.running_mean.add_(0.3)
        net.decoder.heads[0].conv.bias.add_(0.1)
        ref = net(x)[0]
    torch.testing.assert_close(net.disparity(x.clone()).detach(), ref, atol=1e-5, rtol=0)
    with torch.no_grad():
        torch.testing.assert_close(net.disparity(x), ref, atol=1e-5, rtol=0)
    # train() / eval() drop the cache
    net.train()
    assert net._inference_cache is None
    net.eval()
    assert net._inference_cache is None


def test_training_mode_and_autograd_use_the_plain_path() -> None:
    net, x = _net(), _image()
    net.train()
    with torch.no_grad():
        ref = net(x)[0]  # batch statistics
        disp = net.disparity(x)
    torch.testing.assert_close(disp, ref)
    assert net._inference_cache is None
    net.eval()
    disp = net.disparity(x)  # gradients enabled: through the real parameters
    assert disp.requires_grad
    disp.sum().backward()
    assert net.encoder.conv1.weight.grad is not None and net.decoder.heads[0].conv.weight.grad is not None
    assert net._inference_cache is None


def test_fold_batch_norms_leaves_encoder_untouched() -> None:
    net = _net()
    enc = net.encoder
    state = {k: v.clone() for k, v in enc.state_dict().items()}
    fused = fold_batch_norms(enc)
    assert not fused.training and not any(p.requires_grad for p in fused.parameters())
    assert not any(isinstance(m, nn.BatchNorm2d) for m in fused.modules())
    x = _image(2)
    with torch.no_grad():
        for a, b in zip(fused(x), enc(x), strict=True):  # float rounding relative to the features' magnitude
            torch.testing.assert_close(a, b, atol=1e-5 * float(b.abs().max()), rtol=1e-5)
    for k, v in enc.state_dict().items():
        assert torch.equal(v, state[k])
    assert enc.conv1.weight.requires_grad


def test_decoder_scale_subsets() -> None:
    net, x = _net(), _image()
    with torch.no_grad():
        feats = net.encoder(x)
        full = net.decoder(feats)
        coarse = net.decoder(feats, scales=(2, 3))
    assert sorted(coarse) == [2, 3]
    for s in (2, 3):
        torch.testing.assert_close(coarse[s], full[s])
    with pytest.raises(ValueError, match="scales"):
        net.decoder(feats, scales=(4,))
    with pytest.raises(ValueError, match="scales"):
        net.decoder(feats, scales=())
