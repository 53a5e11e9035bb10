"""Edge-aware smoothness of a (mean-normalised) field such as inverse depth."""

from __future__ import annotations

import torch
from kornia.core.check import KORNIA_CHECK_SHAPE


def edge_aware_smoothness(field: torch.Tensor, image: torch.Tensor, normalise: bool = True,
                          eps: float = 1e-7) -> torch.Tensor:
    """``mean |d_x f| exp(-|d_x I|) + mean |d_y f| exp(-|d_y I|)``.

    Args:
        field: (B,C,H,W), e.g. inverse depth (C=1) or flow (C=2).
        image: (B,3,H,W) image at the same resolution; its gradient magnitude (averaged over channels)
            down-weights the penalty at edges.
        normalise: divide the field by its per-image mean first (the paper's mean-normalised inverse
            depth, which removes the trivial shrinking solution).

    Returns:
        scalar tensor.
    """
    KORNIA_CHECK_SHAPE(field, ["B", "C", "H", "W"])
    KORNIA_CHECK_SHAPE(image, ["B", "3", "H", "W"])
    if field.shape[-2:] != image.shape[-2:] or field.shape[0] != image.shape[0]:
        raise ValueError(f"edge_aware_smoothness: field {tuple(field.shape)} and image {tuple(image.shape)} "
                         "must share batch size and resolution")
    if normalise:
        field = field / (field.mean(dim=(2, 3), keepdim=True) + eps)
    dfx = (field[..., :, 1:] - field[..., :, :-1]).abs()
    dfy = (field[..., 1:, :] - field[..., :-1, :]).abs()
    dix = (image[..., :, 1:] - image[..., :, :-1]).abs().mean(1, keepdim=True)
    diy = (image[..., 1:, :] - image[..., :-1, :]).abs().mean(1, keepdim=True)
    return (dfx * torch.exp(-dix)).mean() + (dfy * torch.exp(-diy)).mean()
