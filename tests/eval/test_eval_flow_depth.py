"""Flow metrics (AEPE, Out-N, Fl, pooled sums, the KITTI devkit's filling of sparse predictions), Eigen depth metrics.

The flow file formats are tested in ``tests/data/test_flow_io.py``.
"""

from __future__ import annotations

import math

import pytest
import torch

from dfvo.eval.depth_metrics import compute_depth_metrics
from dfvo.eval.flow_metrics import compute_flow_metrics, flow_error_sums, kitti_fill_invalid, metrics_from_sums


def test_flow_metrics_hand_values() -> None:
    gt = torch.zeros(1, 2, 1, 4)
    pred = torch.zeros(1, 2, 1, 4)
    pred[0, 0, 0] = torch.tensor([0.5, 2.0, 4.0, 10.0])
    m = compute_flow_metrics(pred, gt)
    assert m["aepe"] == pytest.approx(16.5 / 4)
    assert m["out_1"] == pytest.approx(75.0) and m["out_3"] == pytest.approx(50.0) and m["out_5"] == pytest.approx(25.0)
    assert m["fl"] == pytest.approx(50.0) and m["num_pixels"] == 4
    # Fl needs both > 3 px and > 5 % of |gt|: with |gt| = 100 px an error of 4 px is not an outlier.
    gt2 = torch.zeros(1, 2, 1, 4)
    gt2[0, 1] = 100.0
    pred2 = gt2.clone()
    pred2[0, 0, 0] = torch.tensor([0.5, 2.0, 4.0, 10.0])
    assert compute_flow_metrics(pred2, gt2)["fl"] == pytest.approx(25.0)
    valid = torch.tensor([True, True, False, False]).view(1, 1, 1, 4)
    assert compute_flow_metrics(pred, gt, valid)["aepe"] == pytest.approx(1.25)
    with pytest.raises(ValueError, match="no pixel"):
        compute_flow_metrics(pred, gt, torch.zeros_like(valid))


def test_depth_metrics_hand_values() -> None:
    gt = torch.tensor([1.0, 2.0, 4.0]).view(1, 1, 1, 3)
    pred = torch.tensor([2.0, 2.0, 2.0]).view(1, 1, 1, 3)
    m = compute_depth_metrics(pred, gt, median_scaling=False)
    assert m["abs_rel"] == pytest.approx(0.5)
    assert m["sq_rel"] == pytest.approx(2.0 / 3.0)
    assert m["rmse"] == pytest.approx(math.sqrt(5.0 / 3.0))
    assert m["rmse_log"] == pytest.approx(math.sqrt(2 * math.log(2) ** 2 / 3))
    assert m["a1"] == pytest.approx(1 / 3) and m["a2"] == pytest.approx(1 / 3) and m["a3"] == pytest.approx(1 / 3)
    assert m["scale"] == 1.0


def test_depth_median_scaling_and_caps() -> None:
    gt = torch.tensor([[1.0, 2.0, 4.0, 0.0, 100.0]]).view(1, 1, 1, 5)
    pred = gt * 0.5
    m = compute_depth_metrics(pred, gt, max_depth=80.0, median_scaling=True)
    assert m["scale"] == pytest.approx(2.0)  # medians over valid pixels only (0 and 100 m excluded)
    assert m["abs_rel"] == pytest.approx(0.0, abs=1e-12) and m["a1"] == 1.0
    # Predictions are clamped to max_depth: 200 m against 10 m GT counts as 20 m, |20-10|/10 = 1.
    gt2 = torch.tensor([10.0, 10.0]).view(1, 1, 1, 2)
    pred2 = torch.tensor([200.0, 10.0]).view(1, 1, 1, 2)
    m2 = compute_depth_metrics(pred2, gt2, max_depth=20.0, median_scaling=False)
    assert m2["abs_rel"] == pytest.approx((10.0 / 10.0) / 2)
    with pytest.raises(ValueError, match="no image"):
        compute_depth_metrics(pred2, gt2 * 0, median_scaling=False)
    with pytest.raises(ValueError, match=r"\(B,1,H,W\)"):
        compute_depth_metrics(pred2[0], gt2[0])


def test_pooled_sums_equal_metrics_of_the_concatenation() -> None:
    g = torch.Generator().manual_seed(3)
    gt = [torch.randn(1, 2, 5, 7, generator=g) * 10, torch.randn(1, 2, 4, 9, generator=g) * 10]
    pred = [f + torch.randn(f.shape, generator=g) * 3 for f in gt]
    sums = [flow_error_sums(p, t) for p, t in zip(pred, gt)]
    pooled = metrics_from_sums({k: sums[0][k] + sums[1][k] for k in sums[0]})
    flat = lambda xs: torch.cat([x.flatten(2) for x in xs], 2).unsqueeze(2)  # noqa: E731
    whole = compute_flow_metrics(flat(pred), flat(gt))
    assert pooled == pytest.approx(whole)
    assert metrics_from_sums(flow_error_sums(pred[0], gt[0], torch.zeros(1, 1, 5, 7, dtype=torch.bool)))["aepe"] is None


def test_kitti_fill_invalid_hand_example() -> None:
    """Rows: interior holes take the component-wise min of their neighbours, ends copy the nearest valid pixel;
    rows with no valid pixel above / below copy the first / last row that has one; interior empty rows stay 0."""
    u = torch.tensor([[0.0, 0, 0, 0, 0],
                      [0, 5, 0, 0, 2],
                      [0, 0, 0, 0, 0],
                      [7, 0, 3, 0, 0],
                      [0, 0, 0, 0, 0]])
    v = -u
    valid = torch.zeros(1, 5, 5, dtype=torch.bool)
    valid[0, 1, 1] = valid[0, 1, 4] = valid[0, 3, 0] = valid[0, 3, 2] = True
    flow, filled = kitti_fill_invalid(torch.stack([u, v]), valid)
    expect_u = torch.tensor([[5.0, 5, 2, 2, 2],
                             [5, 5, 2, 2, 2],
                             [0, 0, 0, 0, 0],
                             [7, 3, 3, 3, 3],
                             [7, 3, 3, 3, 3]])
    expect_v = torch.tensor([[-5.0, -5, -5, -5, -2],
                             [-5, -5, -5, -5, -2],
                             [0, 0, 0, 0, 0],
                             [-7, -7, -3, -3, -3],
                             [-7, -7, -3, -3, -3]])
    assert torch.equal(flow[0], expect_u) and torch.equal(flow[1], expect_v)
    assert filled[0].all(1).tolist() == [True, True, False, True, True]
    same, same_valid = kitti_fill_invalid(torch.stack([u, v]), torch.ones_like(valid))
    assert torch.equal(same, torch.stack([u, v])) and bool(same_valid.all())
