"""The Levenberg-Marquardt core shared by the PnP and essential-matrix refinements, on curve fits with known
minima: each problem of the batch converges on its own, inactive problems are returned as given."""

from __future__ import annotations

import torch

from dfvo.geometry.lm import levenberg_marquardt


def test_core_fits_a_batch_of_exponentials_independently() -> None:
    x = torch.linspace(0, 2, 40, dtype=torch.float64)
    truth = torch.tensor([[2.0, -1.3], [0.5, 0.8], [1.0, 0.0], [3.0, -0.2]], dtype=torch.float64)
    y = truth[:, :1] * torch.exp(truth[:, 1:] * x)  # (B,40): y = a exp(b x), exactly

    def evaluate(state: tuple[torch.Tensor, ...]) -> tuple[torch.Tensor, tuple[torch.Tensor, ...]]:
        p = state[0]
        e = torch.exp(p[:, 1:] * x)
        r = p[:, :1] * e - y
        return (r * r).sum(-1), (r, e)

    def linearise(state: tuple[torch.Tensor, ...], aux: tuple[torch.Tensor, ...]
                  ) -> tuple[torch.Tensor, torch.Tensor, tuple[torch.Tensor, ...]]:
        r, e = aux
        J = torch.stack([e, state[0][:, :1] * x * e], -1)  # (B,40,2)
        return J.transpose(1, 2) @ J, (J * r[..., None]).sum(1), ()

    def retract(state: tuple[torch.Tensor, ...], delta: torch.Tensor, frame: tuple[torch.Tensor, ...]
                ) -> tuple[torch.Tensor, ...]:
        return (state[0] + delta,)

    start = torch.tensor([[1.0, 0.0], [1.0, 0.0], [1.0, 0.0], [1.0, 0.0]], dtype=torch.float64)
    active = torch.tensor([True, True, True, False])
    (p,), cost = levenberg_marquardt((start,), evaluate, linearise, retract, active, iterations=100,
                                     lambda_init=1e-3, tol=1e-15, max_lambda=1e6, diagonal_floor=1e-12, ridge=1e-12)
    assert torch.allclose(p[:2], truth[:2], atol=1e-8) and bool((cost[:2] < 1e-20).all())
    assert torch.equal(p[2], truth[2])  # started at its minimum (cost 0): never moved
    assert torch.equal(p[3], start[3])  # inactive: returned as given
