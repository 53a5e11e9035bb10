"""A run's outputs (issue 16, training row): the smoke preset, the monitored metric present when a run is stopped by
max_steps mid-epoch, and the small weights-only export beside last.ckpt that inference loads. Also the precision and
memory-layout choices (issue 15 §3)."""

from __future__ import annotations

import json
import runpy
import sys
import warnings
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_module
from safetensors import safe_open

from dfvo.training.runner import build_trainer, run_training

REPO = Path(__file__).resolve().parents[2]
# 8 frames -> 6 depth snippets, batch 1: trainer=smoke's 3 steps stop mid-epoch, before Lightning's epoch-end validation
TINY = ["data.height=64", "data.width=128", "data.batch_size=1", "data.num_frames=8", "data.seeds=[0]",
        "data.val_num_frames=3", "threads=1", "trainer.logger=false"]
MISSING_METRIC = "could not find the monitored key"


def _cfg(tmp_path: Path, *overrides: str):
    with initialize_config_module("dfvo.conf.train", version_base="1.3"):
        return compose("train", overrides=[f"runs_dir={tmp_path}", *TINY, *overrides])


def _run(cfg) -> tuple[dict, list[str]]:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = run_training(cfg)
    return out, [str(w.message) for w in caught]


def _meta(path: str | Path) -> tuple[dict[str, str], set[torch.dtype]]:
    with safe_open(str(path), framework="pt") as f:
        return dict(f.metadata()), {f.get_tensor(k).dtype for k in f.keys() if "num_batches" not in k}


def test_smoke_run_validates_at_its_stop_and_exports_depth_weights(tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """trainer=smoke stops at step 3, mid-epoch: its last step is validated, so the best checkpoint (when kept:
    trainer.keep_best=true) holds the monitored metric (no "monitored key" warning); without validate_at_stop the
    metric is missing, as before."""
    out, messages = _run(_cfg(tmp_path, "model=depth_mono", "trainer=smoke", "trainer.keep_best=true", "name=smoke"))
    assert out["global_step"] == 3
    assert "val/abs_rel_med" in out["metrics"] and 0 < out["metrics"]["val/abs_rel_med"] < 1
    assert Path(out["best_ckpt"]).name == "best-epoch=0-step=3.ckpt"
    best = torch.load(out["best_ckpt"], map_location="cpu", weights_only=False)["callbacks"]
    scores = [float(v["best_model_score"]) for k, v in best.items() if "'val/abs_rel_med'" in k]
    assert scores == pytest.approx([out["metrics"]["val/abs_rel_med"]])
    assert not [m for m in messages if MISSING_METRIC in m]

    # the weights-only export beside the resumable checkpoint: the DepthNet in fp16 with its metadata
    weights, last = Path(out["weights"]), Path(out["last_ckpt"])
    assert weights == tmp_path / "smoke" / "weights.safetensors" and last.parent.parent == weights.parent
    meta, dtypes = _meta(weights)
    assert meta["task"] == "depth" and meta["dfvo_model"] == "depth:depth_mono"
    assert (meta["height"], meta["width"], meta["global_step"]) == ("64", "128", "3")
    assert (float(meta["min_depth"]), float(meta["max_depth"])) == (0.1, 100.0) and meta["source"] == str(last)
    assert dtypes == {torch.float16} and weights.stat().st_size < last.stat().st_size / 5
    # loadable as infer.py's depth source: the same depth as the trained module up to fp16 rounding
    from dfvo.sources.networks import NetworkDepth
    source = NetworkDepth(weights)
    assert source.input_size == (64, 128)
    x = torch.rand(2, 3, 64, 128, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        ref = out["module"].eval()(x)
    rel = ((source(x) - ref).abs() / ref).max()
    assert rel < 1e-2, rel
    # scripts/export_checkpoint.py on last.ckpt (size read from the checkpoint) writes the same tensors and metadata
    exported = tmp_path / "exported.safetensors"
    monkeypatch.setattr(sys, "argv", ["export_checkpoint.py", "depth", str(last), str(exported)])
    runpy.run_path(str(REPO / "scripts" / "export_checkpoint.py"), run_name="__main__")
    assert _meta(exported) == (meta, dtypes)
    with safe_open(str(exported), framework="pt") as a, safe_open(str(weights), framework="pt") as b:
        assert set(a.keys()) == set(b.keys()) and all(torch.equal(a.get_tensor(k), b.get_tensor(k)) for k in a.keys())

    control, messages = _run(_cfg(tmp_path, "model=depth_mono", "trainer=smoke", "trainer.validate_at_stop=false",
                                  "trainer.keep_best=true", "trainer.export_weights=false", "name=control"))
    assert control["global_step"] == 3 and "val/abs_rel_med" not in control["metrics"]
    assert [m for m in messages if MISSING_METRIC in m] and control["weights"] is None
    assert not (tmp_path / "control" / "weights.safetensors").exists()


def test_flow_weights_export_runs_in_infer(tmp_path: Path, infer_cli) -> None:
    """model=flow_supervised trainer=smoke writes weights.safetensors that `infer.py flow.checkpoint=...` runs."""
    out, _ = _run(_cfg(tmp_path, "model=flow_supervised", "model.variant=tiny", "trainer=smoke", "data.width=96",
                       "data.num_frames=6", "name=flow"))
    assert out["global_step"] == 3 and "val/epe" in out["metrics"]
    # trainer=smoke keeps only what resuming needs (issue 28): last.ckpt, no best-*.ckpt copy
    assert [p.name for p in (tmp_path / "flow" / "checkpoints").iterdir()] == ["last.ckpt"]
    meta, dtypes = _meta(out["weights"])
    assert (meta["task"], meta["variant"], meta["height"], meta["width"], meta["global_step"]) == \
        ("flow", "tiny", "64", "96", "3")
    assert dtypes == {torch.float16}
    run = tmp_path / "infer"
    infer_cli("flow=network", f"flow.checkpoint={out['weights']}", "depth=oracle", "data.num_frames=4",
              f"out_dir={run}", "progress=false", "num_threads=1")
    summary = json.loads((run / "summary.json").read_text())
    assert summary["sources"]["flow"] == "network" and summary["sources"]["flow_checkpoint"] == out["weights"]
    assert summary["frames_written"] == 4


def test_precision_and_channels_last_on_cpu(tmp_path: Path) -> None:
    """bf16-mixed and channels_last train on the CPU (accelerator auto); channels_last leaves the values unchanged
    (same first loss) while the convolution weights are NHWC."""
    common = ["model=flow_supervised", "model.variant=tiny", "data.width=96", "data.num_frames=4", "data.val_seeds=[]",
              "trainer.max_steps=1", "trainer.export_weights=false"]
    plain = run_training(_cfg(tmp_path, *common, "name=plain"))
    nhwc = run_training(_cfg(tmp_path, *common, "trainer.channels_last=true", "name=nhwc"))
    convs = [m.weight for m in nhwc["module"].modules() if isinstance(m, torch.nn.Conv2d)]
    assert convs and all(w.is_contiguous(memory_format=torch.channels_last) for w in convs if w.shape[-1] > 1)
    torch.testing.assert_close(nhwc["metrics"]["train/loss"], plain["metrics"]["train/loss"], rtol=1e-4, atol=1e-5)
    bf16 = run_training(_cfg(tmp_path, *common, "trainer.precision=bf16-mixed", "name=bf16"))
    assert torch.isfinite(torch.tensor(bf16["metrics"]["train/loss"]))
    assert abs(bf16["metrics"]["train/loss"] - plain["metrics"]["train/loss"]) < 0.05 * plain["metrics"]["train/loss"]
    trainer = build_trainer(_cfg(tmp_path, "trainer=default"), tmp_path / "t")
    assert type(trainer.accelerator).__name__ == ("CUDAAccelerator" if torch.cuda.is_available() else "CPUAccelerator")


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the message on a machine without a GPU")
def test_gpu_preset_without_gpu_says_so(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"^trainer.accelerator=gpu needs a CUDA GPU and torch sees none; use "):
        build_trainer(_cfg(tmp_path, "trainer=gpu"), tmp_path / "t")
