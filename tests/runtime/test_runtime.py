"""The CPU runtimes (dfvo.sources.runtime): ONNX Runtime and OpenVINO against PyTorch eager on the shipped networks, the
missing-extra line, stale-export detection, and an infer.py run with the runtime against eager.

Tolerances: the runtimes compute the same fp32 graph with other kernels and summation orders (oneDNN, MLAS,
OpenVINO's own), so results differ by float rounding only. On KITTI frames the shipped flow network's outputs
differed from eager by at most 7e-5 px and the depth network's by 1.1e-4 relative (benchmarks/runtime_nets.py,
docs/speed.md); the asserted bounds (1e-3 px, 1e-3 relative) leave ~10x for other CPUs' kernels, and stay ~100x
below anything the tracker could notice (its forward-backward test is at 0.1 px).
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("onnxruntime", reason="the 'fast' extra (pip install -e '.[fast]')")
pytest.importorskip("openvino", reason="the 'fast' extra (pip install -e '.[fast]')")
pytest.importorskip("onnxscript", reason="the 'fast' extra (pip install -e '.[fast]')")

from safetensors.torch import save_file  # noqa: E402

from dfvo.io.checkpoint import find_checkpoint  # noqa: E402
from dfvo.sources.config import RuntimeConfig  # noqa: E402
from dfvo.sources.networks import NetworkDepth, NetworkFlow  # noqa: E402
from dfvo.sources.runtime.engines import cpu_flags, require_runtime  # noqa: E402
from dfvo.sources.runtime.export import ExportSpec, exported_model, read_metadata  # noqa: E402
from dfvo.synthetic import SyntheticWorld  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
FLOW, DEPTH = find_checkpoint("checkpoints/flow.safetensors"), find_checkpoint("checkpoints/depth.safetensors")
needs_checkpoints = pytest.mark.skipif(not (FLOW.is_file() and DEPTH.is_file()), reason="no shipped checkpoints")


@pytest.fixture(scope="module")
def cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One export cache for the module: each shipped network is exported once."""
    return tmp_path_factory.mktemp("runtime_cache")


@pytest.fixture(scope="module")
def pair() -> tuple[torch.Tensor, torch.Tensor]:
    """Two consecutive frames (1,3,192,640) of a synthetic drive (a fixed input with real motion)."""
    world = SyntheticWorld(seed=3, num_frames=3, scenario="drive", height=192, width=640)
    return world.image(0)[None], world.image(1)[None]


@needs_checkpoints
@pytest.mark.slow  # ~100 s on 2 cores (the flow network's export); the fast cover: the depth network's below
@pytest.mark.parametrize("kind", ["onnxruntime", "openvino"])
def test_runtime_flow_agrees_with_eager(kind: str, cache: Path, pair: tuple[torch.Tensor, torch.Tensor]) -> None:
    torch.set_num_threads(1)
    eager = NetworkFlow(FLOW)
    fast = NetworkFlow(FLOW, runtime=RuntimeConfig(kind=kind, cache_dir=str(cache)))
    assert (eager.runtime, fast.runtime) == ("torch", kind)
    ref, got = eager(*pair), fast(*pair)
    for r, g in zip(ref, got):
        assert g.shape == r.shape == (1, 2, 192, 640)
        assert r.abs().max() > 1.0  # real motion, not a zero field
        epe = (g - r).norm(dim=1)
        assert epe.max() < 1e-3, f"{kind}: flow differs from eager by up to {epe.max():.2e} px"


@needs_checkpoints
def test_openvino_runs_on_torchs_threads_of_the_moment(cache: Path, pair: tuple[torch.Tensor, torch.Tensor]) -> None:
    """The engine is built before the loop; the loop's two-thread layout then gives the network thread one torch
    thread: OpenVINO compiles for the thread count of each call (one compiled model per count), the same numbers."""
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        src = NetworkDepth(DEPTH, runtime=RuntimeConfig(kind="openvino", cache_dir=str(cache)))
        engine = next(iter(src._runtime.engines.values()))
        images = torch.cat(pair)
        two = src(images)
        torch.set_num_threads(1)
        one = src(images)
        counts = sorted(int(r.get_compiled_model().get_property("INFERENCE_NUM_THREADS"))
                        for r in engine.compiled.values())
        assert counts == [1, 2] and torch.allclose(one, two, rtol=1e-4)
    finally:
        torch.set_num_threads(threads)


@needs_checkpoints
@pytest.mark.parametrize("kind", ["onnxruntime", "openvino"])
def test_runtime_depth_agrees_with_eager(kind: str, cache: Path, pair: tuple[torch.Tensor, torch.Tensor]) -> None:
    torch.set_num_threads(1)
    images = torch.cat(pair)
    ref = NetworkDepth(DEPTH)(images)
    got = NetworkDepth(DEPTH, runtime=RuntimeConfig(kind=kind, cache_dir=str(cache)))(images)
    assert got.shape == ref.shape == (2, 1, 192, 640)
    rel = ((got - ref).abs() / ref).max()
    assert rel < 1e-3, f"{kind}: depth differs from eager by up to {rel:.2e} (relative)"


def test_missing_extra_is_one_line_naming_it(monkeypatch: pytest.MonkeyPatch) -> None:
    """Without openvino installed, asking for it fails before anything is built, naming the setting and the extra."""
    monkeypatch.setitem(sys.modules, "openvino", None)  # find_spec then says: not installed
    with pytest.raises(ImportError) as err:
        require_runtime("openvino", "flow.runtime.kind")
    text = str(err.value)
    assert "\n" not in text and "flow.runtime.kind=openvino" in text and 'pip install "dfvo[fast]"' in text
    assert "openvino not installed" in text
    if FLOW.is_file():
        with pytest.raises(ImportError, match=r"flow\.runtime\.kind=openvino needs the 'fast' extra"):
            NetworkFlow(FLOW, runtime=RuntimeConfig(kind="openvino"))


def test_missing_extra_on_the_command_line(tmp_path: Path) -> None:
    """``infer.py runtime=openvino`` where openvino cannot be imported: exit 1, one line on stderr naming the extra."""
    code = ("import runpy, sys; sys.modules['openvino'] = None; sys.argv = ['infer.py'] + sys.argv[1:]; "
            f"runpy.run_path({str(REPO / 'infer.py')!r}, run_name='__main__')")
    proc = subprocess.run([sys.executable, "-c", code, "runtime=openvino", "flow=network", "depth=network",
                           "data.num_frames=3", f"out_dir={tmp_path / 'out'}", "progress=false"],
                          cwd=tmp_path, capture_output=True, text=True, timeout=120,
                          env=dict(os.environ, OMP_NUM_THREADS="1"))
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert proc.returncode == 1 and len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert "runtime.kind=openvino needs the 'fast' extra" in lines[0] and 'pip install "dfvo[fast]"' in lines[0]


def _perturbed_depth_checkpoint(path: Path) -> Path:
    """The shipped depth checkpoint with its disparity head's bias moved (other weights, other depth)."""
    from safetensors.torch import load_file

    state = load_file(str(DEPTH))
    key = next(k for k in state if k.endswith("heads.0.conv.bias"))
    state[key] = state[key] + 0.5
    save_file(state, str(path), metadata={"height": "96", "width": "320"})
    return path


@needs_checkpoints
def test_stale_export_is_detected_and_redone(tmp_path: Path, cache: Path, caplog: pytest.LogCaptureFixture,
                                             pair: tuple[torch.Tensor, torch.Tensor]) -> None:
    """A cached export whose recorded checkpoint hash does not match the checkpoint (retrained in place, or an export
    copied in from elsewhere) is not used: it is exported again, and the new export computes the new weights."""
    torch.set_num_threads(1)
    shipped = NetworkDepth(DEPTH, runtime=RuntimeConfig(kind="onnxruntime", cache_dir=str(cache)))
    shipped_export = exported_model(shipped.export_spec((96, 320)), lambda: shipped.model, cache)
    ckpt = _perturbed_depth_checkpoint(tmp_path / "depth.safetensors")
    stale_cache = tmp_path / "cache"
    eager = NetworkDepth(ckpt)
    spec = eager.export_spec((96, 320))
    stale_cache.mkdir()
    (stale_cache / spec.file_name()).write_bytes(shipped_export.read_bytes())  # the shipped weights' export
    caplog.set_level("WARNING", logger="dfvo.sources.runtime")
    fast = NetworkDepth(ckpt, runtime=RuntimeConfig(kind="onnxruntime", cache_dir=str(stale_cache)))
    stale = [r.getMessage() for r in caplog.records if "stale export" in r.getMessage()]
    assert len(stale) == 1 and "checkpoint_sha256" in stale[0] and "\n" not in stale[0]
    recorded = read_metadata(stale_cache / spec.file_name())
    assert recorded["checkpoint_sha256"] == hashlib.sha256(ckpt.read_bytes()).hexdigest()
    images = torch.cat(pair)
    got, want, old = fast(images), eager(images), shipped(images)
    assert ((got - want).abs() / want).max() < 1e-3 and ((old - want).abs() / want).max() > 0.05


def test_stale_settings_or_unreadable_file_are_exported_again(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                             caplog: pytest.LogCaptureFixture) -> None:
    """The cache's decision alone (the export itself replaced by a recorder): a matching record is used as it is; a
    record with another export setting, or a file that is not an ONNX model, is exported again."""
    import onnx
    from onnx import helper

    import dfvo.sources.runtime.export as export

    ckpt = tmp_path / "net.safetensors"
    ckpt.write_bytes(b"weights")
    spec = ExportSpec("depth", ckpt, (64, 96), min_depth=0.1, max_depth=100.0)
    calls: list[dict[str, str]] = []

    def fake_export(net: object, spec: ExportSpec, path: Path, metadata: dict[str, str]) -> Path:
        calls.append(metadata)
        model = helper.make_model(helper.make_graph([], "g", [], []))
        for k, v in metadata.items():
            model.metadata_props.add(key=k, value=v)
        onnx.save(model, str(path))
        return path

    monkeypatch.setattr(export, "export_onnx", fake_export)
    caplog.set_level("WARNING", logger="dfvo.sources.runtime")
    path = exported_model(spec, lambda: None, tmp_path / "cache")
    assert len(calls) == 1 and read_metadata(path) == spec.metadata()
    assert exported_model(spec, lambda: None, tmp_path / "cache") == path and len(calls) == 1  # up to date: used
    model = onnx.load(str(path))
    next(p for p in model.metadata_props if p.key == "max_depth").value = "80.0"
    onnx.save(model, str(path))
    exported_model(spec, lambda: None, tmp_path / "cache")
    assert len(calls) == 2 and any("max_depth" in r.getMessage() for r in caplog.records)
    path.write_bytes(b"not an onnx model")
    exported_model(spec, lambda: None, tmp_path / "cache")
    assert len(calls) == 3 and read_metadata(path) == spec.metadata()


def test_unwritable_cache_is_one_line(tmp_path: Path) -> None:
    """A cache folder that cannot be made refuses with one line naming the setting (nothing is silently skipped)."""
    blocker = tmp_path / "file"
    blocker.write_text("x")
    ckpt = tmp_path / "net.safetensors"
    ckpt.write_bytes(b"weights")
    with pytest.raises(OSError) as err:
        exported_model(ExportSpec("depth", ckpt, (64, 96), min_depth=0.1, max_depth=100.0), lambda: None,
                       blocker / "cache", "depth.runtime.cache_dir")
    assert "\n" not in str(err.value) and str(err.value).startswith(f"depth.runtime.cache_dir={blocker / 'cache'}")


@needs_checkpoints
@pytest.mark.slow  # the flow network's export costs ~50 s on 2 cores; the export code's fast cover is the depth
# network's (test_runtime_depth_agrees_with_eager, test_stale_export_is_detected_and_redone)
def test_export_command_reuses_the_cache(cache: Path) -> None:
    """``python -m dfvo.sources.runtime flow``: the file the flow source uses, recording the shipped file's sha256."""
    proc = subprocess.run([sys.executable, "-m", "dfvo.sources.runtime", "flow", "--cache-dir", str(cache)],
                          capture_output=True, text=True, timeout=600, env=dict(os.environ, OMP_NUM_THREADS="1"))
    assert proc.returncode == 0, proc.stderr
    path = Path(proc.stdout.strip())
    assert path.parent == cache and path.name.startswith("flow-small-flow-") and path.name.endswith("96x320.onnx")
    meta = read_metadata(path)
    assert meta["checkpoint_sha256"] == hashlib.sha256(FLOW.read_bytes()).hexdigest()
    assert (meta["network"], meta["variant"], meta["input_size"]) == ("flow", "small", "96x320")


def _run(infer_cli, tmp_path: Path, name: str, cache: Path, *overrides: str) -> tuple[np.ndarray, dict]:
    """infer.py on 8 frames of the synthetic drive (1 thread): its poses (N,3,4) and summary."""
    out = tmp_path / name
    infer_cli("data.num_frames=8", f"out_dir={out}", "progress=false", "num_threads=1",
              f"flow.runtime.cache_dir={cache}", f"depth.runtime.cache_dir={cache}", *overrides)
    summary = json.loads((out / "summary.json").read_text())
    return np.loadtxt(out / Path(summary["pose_file"]).name).reshape(-1, 3, 4), summary


def _differences(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per pose: position difference (m) and rotation angle between the two (degrees)."""
    dt = np.linalg.norm(a[:, :, 3] - b[:, :, 3], axis=1)
    rel = np.einsum("nij,nkj->nik", a[:, :, :3], b[:, :, :3])
    return dt, np.degrees(np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1)))


@needs_checkpoints
@pytest.mark.slow  # ~20 s; fast covers: the networks on each runtime (test_runtime_depth_agrees_with_eager) and the
# runtime settings through infer.py's command line (test_missing_extra_on_the_command_line)
@pytest.mark.parametrize("kind", ["onnxruntime", "openvino"])
def test_infer_with_runtime_depth_equals_eager(kind: str, tmp_path: Path, cache: Path, infer_cli) -> None:
    """infer.py with the depth network on the runtime (true flow, so the depth is the only difference): the poses
    are eager PyTorch's up to float rounding, and summary.json says which runtime ran."""
    eager, s_eager = _run(infer_cli, tmp_path, "torch", cache, "flow=oracle", "depth=network", "runtime=torch")
    fast, s_fast = _run(infer_cli, tmp_path, kind, cache, "flow=oracle", "depth=network", f"runtime={kind}")
    assert (s_eager["sources"]["depth_runtime"], s_fast["sources"]["depth_runtime"]) == ("torch", kind)
    assert eager.shape == fast.shape == (8, 3, 4) and np.linalg.norm(eager[-1, :, 3]) > 1.0  # the camera moved
    dt, angle = _differences(eager, fast)
    assert dt.max() < 1e-4 and angle.max() < 1e-3, (dt, angle)


@needs_checkpoints
@pytest.mark.slow
def test_infer_with_runtime_flow_close_to_eager(tmp_path: Path, cache: Path, infer_cli) -> None:
    """infer.py with the flow network on OpenVINO (true depth) on the straight world: close to eager, not equal (the
    runtimes' ~1e-5 px flow differences move the tracker's RANSAC draws). Measured 2026-12-02 (8 frames, 1 thread):
    at most 9 mm and 0.004 deg apart a pose, RPE 0.0195 (eager) / 0.0184 m (OpenVINO). Not the drive world: there the
    network's flow leaves the tracker at ~0.11 m RPE a frame and any perturbation (another thread count, another
    runtime) moves the first step by 0.2-0.5 deg, so poses there measure the tracker's chaos, not the runtime.
    Bounds: 3 cm and 0.05 deg a pose, 0.005 m of RPE."""
    args = ("flow=network", "depth=oracle", "seq=straight")
    eager, s_eager = _run(infer_cli, tmp_path, "torch", cache, *args, "runtime=torch")
    fast, s_fast = _run(infer_cli, tmp_path, "openvino", cache, *args, "runtime=openvino")
    assert s_fast["sources"]["flow_runtime"] == "openvino" and s_eager["sources"]["flow_runtime"] == "torch"
    dt, angle = _differences(eager, fast)
    assert dt.max() < 0.03 and angle.max() < 0.05, (dt, angle)
    assert abs(s_fast["metrics"]["rpe_m"] - s_eager["metrics"]["rpe_m"]) < 0.005


def test_bf16_only_where_the_cpu_and_runtime_have_it(monkeypatch: pytest.MonkeyPatch) -> None:
    """``runtime.precision=bf16`` is refused with one line on a CPU without bf16 instructions (flags read, never
    assumed) and on a runtime other than OpenVINO."""
    import dfvo.sources.runtime.engines as engines

    monkeypatch.setattr(engines, "cpu_flags", lambda: {"avx2", "avx512f"})
    with pytest.raises(ValueError, match=r"^depth\.runtime\.precision=bf16: this CPU has no bf16 instructions"):
        engines.check_precision("openvino", "bf16", "depth.runtime.precision")
    monkeypatch.setattr(engines, "cpu_flags", lambda: {"avx512_bf16"})
    engines.check_precision("openvino", "bf16", "depth.runtime.precision")
    with pytest.raises(ValueError, match=r"^depth\.runtime\.precision=bf16 needs the openvino runtime"):
        engines.check_precision("onnxruntime", "bf16", "depth.runtime.precision")
    with pytest.raises(ValueError, match=r"^flow\.runtime\.precision='fp16'; expected one of"):
        engines.check_precision("openvino", "fp16", "flow.runtime.precision")


@needs_checkpoints
@pytest.mark.skipif(not {"avx512_bf16", "amx_bf16"} & cpu_flags(), reason="this CPU has no bf16 instructions")
def test_openvino_bf16_depth_close_to_eager(cache: Path, pair: tuple[torch.Tensor, torch.Tensor]) -> None:
    """OpenVINO in bf16 (8-bit mantissa): depth within 3 % of eager's everywhere (KITTI 06/07: 0.13-0.19 % mean,
    1.5 % max, benchmarks/runtime_nets.py), far below the network's own error against stereo (~19 %)."""
    torch.set_num_threads(1)
    images = torch.cat(pair)
    ref = NetworkDepth(DEPTH)(images)
    fast = NetworkDepth(DEPTH, runtime=RuntimeConfig(kind="openvino", precision="bf16", cache_dir=str(cache)))
    assert fast.runtime == "openvino-bf16"
    rel = ((fast(images) - ref).abs() / ref)
    assert rel.max() < 0.03 and rel.mean() < 0.005 and rel.max() > 0  # bf16 really ran (not fp32)
