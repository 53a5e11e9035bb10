"""task=flow: metrics of dfvo.source_eval.flow against a straightforward numpy implementation (files decoded by
OpenCV), on the real KITTI 2015 pair and on synthetic KITTI-2012 fixtures; sources, BestN selection, errors."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf
from PIL import Image

from dfvo.data.flow_datasets import resize_flow
from dfvo.data.flow_io import write_kitti_flow
from dfvo.data.image_io import read_image
from dfvo.data.transforms import resize_image
from dfvo.matching.flow_refinement import FlowRefinementConfig, refine_forward_backward
from dfvo.source_eval.config import FlowSelectionEvalConfig
from dfvo.source_eval.flow import evaluate_flow_task, format_flow_table, selection_mask
from dfvo.sources import find_checkpoint
from dfvo.sources.dis import DISFlow
from dfvo.sources.networks import NetworkFlow

cv2 = pytest.importorskip("cv2")
KITTI = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "flow_samples" / "kitti_flow" / "training"


def _kitti() -> Path:
    if not KITTI.exists():
        pytest.skip(f"needs {KITTI} (the project's ../shared data folder); not present on this machine")
    return KITTI


def _cfg(gt: Path, pred: Path | None = None, **flow) -> OmegaConf:
    return OmegaConf.create({"task": "flow", "gt_dir": str(gt), "pred_dir": str(pred) if pred else None,
                             "flow": flow})


def _cv_flow(path: Path) -> tuple[np.ndarray, np.ndarray]:
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED).astype(np.float64)  # B = valid, G = v, R = u
    return (raw[..., [2, 1]] - 2**15) / 64.0, raw[..., 0] > 0


def _np_errors(pred: np.ndarray, gt: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    epe = np.sqrt(((pred - gt) ** 2).sum(-1))[valid]
    return epe, np.sqrt((gt**2).sum(-1))[valid]


def _np_summary(errors: list[tuple[np.ndarray, np.ndarray]]) -> dict[str, float]:
    epe = np.concatenate([e for e, _ in errors])
    mag = np.concatenate([m for _, m in errors])
    return {"aepe": float(np.mean([e.mean() for e, _ in errors])), "aepe_pixels": float(epe.mean()),
            "out_1": 100 * float((epe > 1).mean()), "out_3": 100 * float((epe > 3).mean()),
            "fl_all": 100 * float(((epe > 3) & (epe / np.maximum(mag, 1e-300) > 0.05)).mean())}


def _check(block: dict, ref: dict[str, float]) -> None:
    for key, value in ref.items():
        assert block[key] == pytest.approx(value, rel=1e-9, abs=1e-9), key


def test_real_kitti_pair_precomputed_prediction(tmp_path: Path) -> None:
    gt_dir = _kitti()
    gt, valid = _cv_flow(gt_dir / "flow_occ" / "000000_10.png")
    H, W = valid.shape
    rng = np.random.default_rng(0)
    # a dense prediction: the true flow where known (a smooth field elsewhere) plus errors of every size
    dense = np.where(valid[..., None], gt, 0.0) + rng.normal(0, 1, (H, W, 2)) * rng.choice([0.2, 2, 20], (H, W, 1))
    write_kitti_flow(tmp_path / "000000_10.png", dense.transpose(2, 0, 1))
    res = evaluate_flow_task(_cfg(gt_dir, tmp_path))
    pred, pred_valid = _cv_flow(tmp_path / "000000_10.png")  # what the file holds (1/64 px steps)
    assert pred_valid.all() and res["source"] == "pred" and res["num_pairs"] == 1
    ref = _np_summary([_np_errors(pred, gt, valid)])
    _check(res["metrics"]["occ"]["all"], ref)
    assert res["metrics"]["occ"]["all"]["num_pixels"] == int(valid.sum()) == 75453
    assert res["metrics"]["occ"]["bestn"] is None and "noc" not in res["metrics"]
    assert 10 < ref["out_1"] < 90 and 1 < ref["fl_all"] < 50  # the check covers both sides of each threshold
    assert "AEPE" in format_flow_table(res)


def _devkit_fill(flow: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """The KITTI devkit's background interpolation, written as plain loops (an independent reference)."""
    f, m = flow.copy(), valid.copy()
    f[~m] = 0
    H, W = m.shape
    for v in range(H):
        count = 0
        for u in range(W):
            if m[v, u]:
                if count >= 1:
                    u1, u2 = u - count, u - 1
                    if u1 > 0 and u2 < W - 1:
                        f[v, u1:u2 + 1] = np.minimum(f[v, u1 - 1], f[v, u2 + 1])
                        m[v, u1:u2 + 1] = True
                count = 0
            else:
                count += 1
        cols = np.flatnonzero(m[v])
        if cols.size:
            f[v, :cols[0]] = f[v, cols[0]]
            f[v, cols[-1] + 1:] = f[v, cols[-1]]
            m[v, :cols[0]] = m[v, cols[-1] + 1:] = True
    for u in range(W):
        rows = np.flatnonzero(m[:, u])
        if rows.size:
            f[:rows[0], u] = f[rows[0], u]
            f[rows[-1] + 1:, u] = f[rows[-1], u]
    return f


def test_real_kitti_sparse_prediction_is_filled_like_the_devkit(tmp_path: Path) -> None:
    gt_dir = _kitti()
    gt, valid = _cv_flow(gt_dir / "flow_occ" / "000000_10.png")
    rng = np.random.default_rng(1)
    H, W = valid.shape
    pred = np.where(valid[..., None], gt, 5.0) + rng.normal(0, 0.8, (H, W, 2))
    pred_valid = rng.random((H, W)) > 0.4
    pred_valid[:40] = False  # rows without any prediction: filled from below
    write_kitti_flow(tmp_path / "000000_10.png", pred.transpose(2, 0, 1), pred_valid)
    stored, stored_valid = _cv_flow(tmp_path / "000000_10.png")
    res = evaluate_flow_task(_cfg(gt_dir, tmp_path, source="pred"))
    _check(res["metrics"]["occ"]["all"], _np_summary([_np_errors(_devkit_fill(stored, stored_valid), gt, valid)]))
    raw = evaluate_flow_task(_cfg(gt_dir, tmp_path, fill_invalid=False))
    _check(raw["metrics"]["occ"]["all"], _np_summary([_np_errors(np.where(stored_valid[..., None], stored, 0.0),
                                                                 gt, valid)]))


def _fixture_2012(root: Path, seed: int) -> dict:
    """Two KITTI-2012 pairs with sparse random ground truth (occ superset of noc) and predictions."""
    rng = np.random.default_rng(seed)
    train, pred_dir = root / "training", root / "pred"
    data = {}
    for k, (H, W) in enumerate([(20, 31), (24, 29)]):
        name = f"{k:06d}"
        for f in ("10", "11"):
            (train / "colored_0").mkdir(parents=True, exist_ok=True)
            img = rng.integers(0, 255, (H, W, 3), dtype=np.uint8)
            Image.fromarray(img).save(train / "colored_0" / f"{name}_{f}.png")
        gt = np.round(rng.normal(0, 15, (2, H, W)) * 64) / 64
        occ = rng.random((H, W)) > 0.3
        noc = occ & (rng.random((H, W)) > 0.3)
        write_kitti_flow(train / "flow_occ" / f"{name}_10.png", gt, occ)
        write_kitti_flow(train / "flow_noc" / f"{name}_10.png", gt, noc)
        pred = gt + rng.normal(0, 1, (2, H, W)) * rng.choice([0.3, 3, 30], (1, H, W))
        write_kitti_flow(pred_dir / f"{name}_10.png", pred)
        data[name] = (train / "flow_occ" / f"{name}_10.png", train / "flow_noc" / f"{name}_10.png",
                      pred_dir / f"{name}_10.png")
    return data


def test_synthetic_fields_two_pairs_both_masks(tmp_path: Path) -> None:
    data = _fixture_2012(tmp_path, 3)
    res = evaluate_flow_task(_cfg(tmp_path / "training", tmp_path / "pred", layout="kitti2012"))
    for mask, idx in (("occ", 0), ("noc", 1)):
        errors = []
        for files in data.values():
            gt, valid = _cv_flow(files[idx])
            pred, _ = _cv_flow(files[2])
            errors.append(_np_errors(pred, gt, valid))
        _check(res["metrics"][mask]["all"], _np_summary(errors))
    assert res["metrics"]["noc"]["all"]["num_pixels"] < res["metrics"]["occ"]["all"]["num_pixels"]
    one = evaluate_flow_task(_cfg(tmp_path / "training", tmp_path / "pred", layout="kitti2012", frames=["000001"]))
    assert one["num_pairs"] == 1 and one["per_pair"][0]["name"] == "000001"
    oracle = evaluate_flow_task(_cfg(tmp_path / "training", layout="kitti2012", source="oracle"))
    assert oracle["metrics"]["occ"]["all"]["aepe"] == 0 and oracle["metrics"]["occ"]["all"]["out_1"] == 0


def test_precomputed_flows_need_no_images(tmp_path: Path) -> None:
    """Issue 28: ``task=flow`` on precomputed flows with only the ground-truth flows beside them evaluates (the
    images are read only when a flow source must run), with the same numbers as with the images there, also from
    the command line; the network source still needs the images and says so."""
    import shutil
    import subprocess
    import sys

    _fixture_2012(tmp_path, 3)
    with_images = evaluate_flow_task(_cfg(tmp_path / "training", tmp_path / "pred", layout="kitti2012"))
    shutil.rmtree(tmp_path / "training" / "colored_0")
    without = evaluate_flow_task(_cfg(tmp_path / "training", tmp_path / "pred", layout="kitti2012"))
    assert without["metrics"] == with_images["metrics"] and without["num_pairs"] == 2
    oracle = evaluate_flow_task(_cfg(tmp_path / "training", layout="kitti2012", source="oracle"))
    assert oracle["metrics"]["occ"]["all"]["aepe"] == 0
    proc = subprocess.run([sys.executable, "-m", "dfvo.evaluate", "task=flow", f"gt_dir={tmp_path / 'training'}",
                           f"pred_dir={tmp_path / 'pred'}", "flow.layout=kitti2012"], cwd=tmp_path,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "flow: pred on kitti2012 (2 pairs)" in proc.stdout
    with pytest.raises(FileNotFoundError, match=r"KITTI 2012 flow images: folder .*colored_0 does not exist"):
        evaluate_flow_task(_cfg(tmp_path / "training", layout="kitti2012", source="dis"))


def test_bestn_rows_use_the_backward_flow(tmp_path: Path) -> None:
    data = _fixture_2012(tmp_path, 4)
    for name, (occ, _, pred_path) in data.items():
        gt, valid = _cv_flow(occ)
        H, W = valid.shape
        shift = np.zeros((2, H, W))
        shift[0] = 1.0
        write_kitti_flow(pred_path, shift)  # forward: one pixel right everywhere
        bwd = -shift.copy()
        bwd[:, :, : W // 2] += 3.0  # backward consistent only on the right half of frame 11
        write_kitti_flow(tmp_path / "pred" / f"{name}_11.png", bwd)
    res = evaluate_flow_task(_cfg(tmp_path / "training", tmp_path / "pred", layout="kitti2012",
                                  selection={"method": "threshold", "max_inconsistency": 0.1}))
    errors = []
    for occ, _, _ in data.values():
        gt, valid = _cv_flow(occ)
        H, W = valid.shape
        pred = np.zeros((H, W, 2))
        pred[..., 0] = 1.0
        sel = np.zeros((H, W), bool)
        sel[:, W // 2 - 1:W - 1] = True  # x + 1 lands in the consistent half (x + 1 >= W // 2) and inside
        errors.append(_np_errors(pred, gt, valid & sel))
    _check(res["metrics"]["occ"]["bestn"], _np_summary(errors))


def test_selection_mask_methods() -> None:
    H, W = 30, 40
    fwd = torch.zeros(2, H, W)
    fwd[0] = 2.0
    bwd = -fwd.clone()
    noise = torch.linspace(0, 1, H * W).view(H, W)
    bwd[1] += noise  # inconsistency grows with the pixel index (row-major)
    sel = FlowSelectionEvalConfig(method="best_n", fraction=0.1, num_correspondences=None, max_inconsistency=0.1,
                                  grid=[3, 4])
    m = selection_mask(fwd, bwd, sel)[0]
    assert int(m.sum()) == 120 and bool(m[0, :38].all()) and not bool(m[:, 38:].any())  # x+2 leaves the image
    m = selection_mask(fwd, bwd, replace(sel, method="threshold"))[0]
    incon = noise.clone()
    incon[:, 38:] = float("inf")
    assert torch.equal(m, incon < 0.1)
    m = selection_mask(fwd, bwd, replace(sel, method="local_best_k", num_correspondences=24))[0]
    assert 0 < int(m.sum()) <= 24 and bool((incon[m] < 0.1).all())


def test_dis_and_network_sources_on_the_real_pair() -> None:
    gt_dir = _kitti()
    res = evaluate_flow_task(_cfg(gt_dir, source="dis", preset="ultrafast", working_size=[96, 320]))
    img1, img2 = read_image(gt_dir / "image_2" / "000000_10.png"), read_image(gt_dir / "image_2" / "000000_11.png")
    fwd, _ = DISFlow("ultrafast")(resize_image(img1, 96, 320)[None], resize_image(img2, 96, 320)[None])
    fwd = resize_flow(fwd[0], torch.ones(1, 96, 320, dtype=torch.bool), (375, 1242))[0]
    gt, valid = _cv_flow(gt_dir / "flow_occ" / "000000_10.png")
    ref = _np_summary([_np_errors(fwd.permute(1, 2, 0).double().numpy(), gt, valid)])
    for key, value in ref.items():
        assert res["metrics"]["occ"]["all"][key] == pytest.approx(value, rel=1e-5), key
    assert res["metrics"]["occ"]["bestn"]["num_pixels"] > 50 and res["source"] == "dis (ultrafast)"
    net = evaluate_flow_task(_cfg(gt_dir, source="network", working_size=[96, 320]))
    assert net["source"] == "network" and np.isfinite(net["metrics"]["occ"]["all"]["aepe"])
    assert net["metrics"]["occ"]["bestn"]["num_pixels"] > 50
    # flow.refine: the network's flow refined as infer.py refines it (at the working size), then scored
    refined = evaluate_flow_task(_cfg(gt_dir, source="network", working_size=[96, 320],
                                      refine={"iterations": 2, "mode": "dense"}))
    a, b = resize_image(img1, 96, 320)[None], resize_image(img2, 96, 320)[None]
    fwd, bwd = NetworkFlow(find_checkpoint("checkpoints/flow.safetensors"), None)(a, b)
    fwd, _ = refine_forward_backward(a, b, fwd, bwd, FlowRefinementConfig(iterations=2, mode="dense"))
    fwd = resize_flow(fwd[0], torch.ones(1, 96, 320, dtype=torch.bool), (375, 1242))[0]
    ref = _np_summary([_np_errors(fwd.permute(1, 2, 0).double().numpy(), gt, valid)])
    for key, value in ref.items():
        assert refined["metrics"]["occ"]["all"][key] == pytest.approx(value, rel=1e-4), key
    assert refined["source"] == "network (refined: dense, 2 iterations)"
    assert refined["metrics"]["occ"]["all"]["aepe"] != net["metrics"]["occ"]["all"]["aepe"]


def test_flow_task_errors(tmp_path: Path) -> None:
    data = _fixture_2012(tmp_path, 5)
    gt = tmp_path / "training"
    with pytest.raises(ValueError, match=r"flow\.bogus: unknown setting"):
        evaluate_flow_task(_cfg(gt, bogus=1))
    with pytest.raises(ValueError, match="flow.layout='kitti2020'"):
        evaluate_flow_task(_cfg(gt, layout="kitti2020"))
    with pytest.raises(FileNotFoundError, match="image_2"):  # kitti2015 layout on 2012 files, a source that must run
        evaluate_flow_task(_cfg(gt, source="network"))
    with pytest.raises(ValueError, match="gt_dir"):
        evaluate_flow_task(OmegaConf.create({"task": "flow"}))
    next(iter(data.values()))[2].unlink()
    with pytest.raises(FileNotFoundError, match="000000_10.png"):
        evaluate_flow_task(_cfg(gt, tmp_path / "pred", layout="kitti2012"))
    with pytest.raises(ValueError, match=r"flow.frames: \['000009'\]"):
        evaluate_flow_task(_cfg(gt, layout="kitti2012", source="oracle", frames=["000009"]))
