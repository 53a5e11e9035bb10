"""Test-time flip averaging of the depth network (``depth.flip_average``)."""

from __future__ import annotations

from pathlib import Path

import torch

from dfvo.sources.networks import NetworkDepth, blend_flipped_inverse_depth


def test_blend_uses_mirror_at_left_border_plain_at_right_and_mean_in_between() -> None:
    w = 101  # u = column / 100
    plain = torch.full((1, 1, 2, w), 2.0)
    mirror = torch.full((1, 1, 2, w), 4.0)
    out = blend_flipped_inverse_depth(plain, mirror, border=0.05)
    assert torch.allclose(out[..., :6], torch.tensor(4.0))      # u <= 0.05: the mirrored prediction only
    assert torch.allclose(out[..., 95:], torch.tensor(2.0))     # u >= 0.95: the plain prediction only
    assert torch.allclose(out[..., 10:91], torch.tensor(3.0))   # 0.1 <= u <= 0.9: the mean
    # u = 0.07 is 40 % along the left ramp: weight 0.6 on the mirror, 0.4 on the mean -> 0.6*4 + 0.4*3
    assert torch.allclose(out[..., 7:8], torch.tensor(0.6 * 4.0 + 0.4 * 3.0), atol=1e-5)
    ramp = out[0, 0, 0, :11]
    assert torch.all(ramp[1:] <= ramp[:-1] + 1e-6)              # monotone from the mirror's value to the mean


def test_flip_averaged_depth_is_mirror_equivariant(tmp_path: Path) -> None:
    """Mirroring the input mirrors the output exactly (each half sees the same two predictions), which the plain
    network does not do."""
    from safetensors.torch import save_file

    from dfvo.models.depth_net import DepthNet

    torch.manual_seed(0)
    path = tmp_path / "depth.safetensors"
    save_file({k: v.contiguous() for k, v in DepthNet().state_dict().items()}, str(path),
              metadata={"height": "64", "width": "128"})
    img = torch.rand(2, 3, 64, 128)
    averaged = NetworkDepth(path, flip_average=True)
    torch.testing.assert_close(averaged(img.flip(-1)), averaged(img).flip(-1), rtol=1e-4, atol=1e-5)
    plain = NetworkDepth(path)
    assert not torch.allclose(plain(img.flip(-1)), plain(img).flip(-1), rtol=1e-3)
    d_plain, d_avg = plain(img), averaged(img)
    centre = slice(20, 108)
    expect = 2.0 / (1.0 / d_plain + 1.0 / plain(img.flip(-1)).flip(-1))
    torch.testing.assert_close(d_avg[..., centre], expect[..., centre], rtol=1e-4, atol=1e-5)


def test_flip_average_setting_reaches_the_depth_source(tmp_path: Path) -> None:
    from safetensors.torch import save_file

    from dfvo.models.depth_net import DepthNet
    from dfvo.sources import DepthSourceConfig, build_depth_source

    path = tmp_path / "depth.safetensors"
    save_file({k: v.contiguous() for k, v in DepthNet().state_dict().items()}, str(path))
    for flag in (True, False):
        cfg = DepthSourceConfig(source="network", checkpoint=str(path), flip_average=flag)
        assert build_depth_source(cfg).flip_average is flag
