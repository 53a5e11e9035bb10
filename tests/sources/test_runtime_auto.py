"""``runtime.kind=auto`` (issue 39): OpenVINO in bf16 only where the CPU has bf16 units and the fast extra is
installed, PyTorch fp32 elsewhere, with the reason; the CPU's flags and the installed packages are stubbed, so the
decision is checked on any machine."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

import dfvo.sources.runtime.engines as engines
from dfvo.io.checkpoint import find_checkpoint
from dfvo.sources.config import RuntimeConfig

DEPTH = find_checkpoint("checkpoints/depth.safetensors")


def _installed(monkeypatch: pytest.MonkeyPatch, present: bool) -> None:
    real = importlib.util.find_spec
    stubbed = {"openvino", "onnx", "onnxscript"}
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: (object() if present else None) if name in stubbed else real(name, *a))


@pytest.mark.parametrize(("flags", "present", "device", "want", "why"), [
    ({"avx512f", "amx_bf16", "avx512_bf16"}, True, "cpu", ("openvino", "bf16"),
     "the CPU has amx_bf16, avx512_bf16 and the 'fast' extra is installed"),
    ({"avx512f", "avx512_bf16"}, False, "cpu", ("torch", "fp32"),
     "the CPU has avx512_bf16 but the 'fast' extra is not installed (onnx, onnxscript, openvino missing"),
    ({"avx2", "avx512f", "avx512_vnni"}, True, "cpu", ("torch", "fp32"), "this CPU has no bf16 instructions"),
    (set(), True, "cpu", ("torch", "fp32"), "this CPU has no bf16 instructions"),  # flags unreadable: never assumed
    ({"avx512_bf16"}, True, "cuda:0", ("torch", "fp32"), "device=cuda:0: the exported runtimes run on the CPU"),
])
def test_auto_decides_from_the_cpu_and_the_extra(monkeypatch: pytest.MonkeyPatch, flags: set[str], present: bool,
                                                device: str, want: tuple[str, str], why: str) -> None:
    monkeypatch.setattr(engines, "cpu_flags", lambda: flags)
    _installed(monkeypatch, present)
    kind, precision, reason = engines.resolve_auto_runtime(device)
    assert (kind, precision) == want and reason.startswith(why), reason


@pytest.mark.skipif(not DEPTH.is_file(), reason="no shipped depth checkpoint")
def test_a_source_with_auto_reports_what_it_runs_and_why(monkeypatch: pytest.MonkeyPatch) -> None:
    """On a CPU without bf16 the depth source runs PyTorch eager and says why (summary.json's depth_runtime and
    depth_runtime_reason)."""
    from dfvo.sources.networks import NetworkDepth

    monkeypatch.setattr(engines, "cpu_flags", lambda: {"avx2"})
    src = NetworkDepth(Path(DEPTH), runtime=RuntimeConfig(kind="auto"))
    assert src.runtime == "torch"
    assert src.runtime_reason.startswith("depth.runtime.kind=auto: this CPU has no bf16 instructions")


def test_the_runtime_groups_set_each_network() -> None:
    """infer.py's default runs both networks on PyTorch; runtime=depth_auto puts the depth network alone on auto
    (runtime/depth_auto.yaml), runtime=auto both."""
    from dfvo.inference.config import compose_infer_config

    kinds = {}
    for overrides in ([], ["runtime=depth_auto"], ["runtime=auto"], ["runtime=torch"]):
        cfg = compose_infer_config(overrides)
        kinds[" ".join(overrides)] = (str(cfg.flow.runtime.kind), str(cfg.depth.runtime.kind))
    assert kinds == {"": ("torch", "torch"), "runtime=depth_auto": ("torch", "auto"), "runtime=auto": ("auto", "auto"),
                     "runtime=torch": ("torch", "torch")}


@pytest.mark.skipif(not DEPTH.is_file(), reason="no shipped depth checkpoint")
def test_auto_falls_back_to_pytorch_where_its_export_cannot_be_written(monkeypatch: pytest.MonkeyPatch,
                                                                       tmp_path: Path) -> None:
    """A default must run: ``auto`` whose export folder cannot be made (a file stands in its place) runs PyTorch and
    says why, with eager's depth to the bit; the same folder with ``openvino`` asked for by name is refused in one
    line naming the setting."""
    pytest.importorskip("openvino", reason="the 'fast' extra (pip install -e '.[fast]')")
    import torch

    from dfvo.sources.networks import NetworkDepth

    monkeypatch.setattr(engines, "resolve_auto_runtime", lambda device="cpu": ("openvino", "fp32", "stubbed"))
    blocked = tmp_path / "not_a_folder"
    blocked.write_text("a file where the cache folder should be")
    src = NetworkDepth(Path(DEPTH), runtime=RuntimeConfig(kind="auto", cache_dir=str(blocked)))
    assert src.runtime == "torch"
    assert src.runtime_reason.startswith("depth.runtime.kind=auto: stubbed; the export failed (depth.runtime."
                                         f"cache_dir={blocked}: cannot write")
    images = torch.rand(2, 3, 96, 320, generator=torch.Generator().manual_seed(0))
    assert torch.equal(src(images), NetworkDepth(Path(DEPTH))(images))
    with pytest.raises(OSError, match=r"^depth\.runtime\.cache_dir=.*cannot write the exported depth network") as err:
        NetworkDepth(Path(DEPTH), runtime=RuntimeConfig(kind="openvino", cache_dir=str(blocked)))
    assert "\n" not in str(err.value)
