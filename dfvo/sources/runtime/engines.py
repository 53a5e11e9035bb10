"""Run an exported network (ONNX) with ONNX Runtime or OpenVINO on the CPU, with torch tensors in and out.

Both take the number of threads torch uses when the engine is built (``num_threads`` of ``infer.py``), run in fp32
(OpenVINO is told so explicitly: on CPUs with bf16 instructions its default would be bf16), and compute the
results of the PyTorch module they replace up to float rounding (``tests/runtime``). OpenVINO compiles one static
model per batch size it meets (a handful in a run: the loop's batch, the first frame, the last batch).

Missing extra: :func:`require_runtime` fails with one line naming the ``fast`` extra.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path
from typing import Protocol

import numpy as np
import torch

__all__ = ["EXTRA", "RUNTIME_PACKAGES", "EXPORT_PACKAGES", "PRECISIONS", "Engine", "cpu_flags", "require_runtime",
           "check_precision", "build_engine", "OnnxRuntimeEngine", "OpenVinoEngine", "resolve_auto_runtime"]

EXTRA = "fast"
"""The optional extra that brings the runtimes: ``pip install "dfvo[fast]"``."""
RUNTIME_PACKAGES = {"onnxruntime": "onnxruntime", "openvino": "openvino"}
EXPORT_PACKAGES = ("onnx", "onnxscript")  # torch.onnx's exporter needs both
PRECISIONS = {"fp32": "f32", "bf16": "bf16"}  # runtime.precision -> OpenVINO's inference precision hint
BF16_FLAGS = ("avx512_bf16", "amx_bf16")


def cpu_flags() -> set[str]:
    """The CPU's instruction-set flags (``/proc/cpuinfo``; empty where it cannot be read): never assumed."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("flags"):
                    return set(line.split(":", 1)[1].split())
    except OSError:
        pass
    return set()


def resolve_auto_runtime(device: str = "cpu") -> tuple[str, str, str]:
    """``(kind, precision, reason)`` of ``runtime.kind=auto`` on this machine: OpenVINO in bf16 where the CPU has
    bf16 instructions (:data:`BF16_FLAGS`) and the ``fast`` extra is installed, else PyTorch in fp32; ``reason``
    says which fact decided, for ``summary.json``."""
    if torch.device(device).type != "cpu":
        return "torch", "fp32", f"device={device}: the exported runtimes run on the CPU"
    have = sorted(cpu_flags() & set(BF16_FLAGS))
    if not have:
        return "torch", "fp32", f"this CPU has no bf16 instructions ({' or '.join(BF16_FLAGS)} not in its flags)"
    missing = [name for name in (*EXPORT_PACKAGES, RUNTIME_PACKAGES["openvino"])
               if importlib.util.find_spec(name) is None]
    if missing:
        return "torch", "fp32", (f"the CPU has {', '.join(have)} but the '{EXTRA}' extra is not installed "
                                 f"({', '.join(missing)} missing: pip install \"dfvo[{EXTRA}]\")")
    return "openvino", "bf16", f"the CPU has {', '.join(have)} and the '{EXTRA}' extra is installed"


def check_precision(kind: str, precision: str, setting: str) -> None:
    """Raise ValueError (one line naming ``setting``) for a precision the runtime or this CPU does not have."""
    if precision not in PRECISIONS:
        raise ValueError(f"{setting}={precision!r}; expected one of {sorted(PRECISIONS)}")
    if precision == "bf16":
        if kind != "openvino":
            raise ValueError(f"{setting}=bf16 needs the openvino runtime (got {kind}); use fp32")
        if not cpu_flags() & set(BF16_FLAGS):
            raise ValueError(f"{setting}=bf16: this CPU has no bf16 instructions ({' or '.join(BF16_FLAGS)} not in "
                             "/proc/cpuinfo's flags); use fp32")


class Engine(Protocol):
    """An exported network: ``engine(*inputs)`` gives the outputs of the graph as float32 CPU tensors."""

    name: str

    def __call__(self, *inputs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        ...


def require_runtime(kind: str, setting: str, need_runtime: bool = True) -> None:
    """Check that the packages of runtime ``kind`` (and of the ONNX export) are installed.

    Raises:
        ImportError: one line naming ``setting``, the missing packages and the extra that brings them.
    """
    wanted = [*EXPORT_PACKAGES, *([RUNTIME_PACKAGES[kind]] if need_runtime else [])]
    missing = [name for name in wanted if importlib.util.find_spec(name) is None]
    if missing:
        raise ImportError(f"{setting}={kind} needs the '{EXTRA}' extra ({', '.join(missing)} not installed): "
                          f"pip install \"dfvo[{EXTRA}]\" (or set {setting}=torch)")


def _numpy(t: torch.Tensor) -> np.ndarray:
    return t.detach().to("cpu", torch.float32).contiguous().numpy()


class OnnxRuntimeEngine:
    """An ONNX model run by ONNX Runtime's CPU provider (all graph optimisations, ``threads`` intra-op threads)."""

    name = "onnxruntime"

    def __init__(self, path: str | Path, threads: int) -> None:
        import onnxruntime as ort

        options = ort.SessionOptions()
        options.intra_op_num_threads = max(1, int(threads))
        options.inter_op_num_threads = 1
        options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        options.log_severity_level = 3
        self.session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
        self.inputs = [i.name for i in self.session.get_inputs()]

    def __call__(self, *inputs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        outs = self.session.run(None, {name: _numpy(t) for name, t in zip(self.inputs, inputs, strict=True)})
        return tuple(torch.from_numpy(o) for o in outs)


class OpenVinoEngine:
    """An ONNX model run by OpenVINO's CPU plugin (latency hint, ``threads`` threads; ``inference_precision`` in
    OpenVINO's own words, ``f32`` or ``bf16``: :data:`PRECISIONS` maps ``runtime.precision`` to it).

    Each batch size compiles a static model (faster to run than one dynamic model); ``compiled_cache`` (a folder)
    keeps OpenVINO's compiled blobs there (its ``CACHE_DIR``), so later runs load them instead of compiling again
    (compiling took ~3-10 s per shape on the 2-core machine)."""

    name = "openvino"

    def __init__(self, path: str | Path, threads: int | None, inference_precision: str = "f32",
                 compiled_cache: str | Path | None = None) -> None:
        import openvino as ov

        self.core = ov.Core()
        if compiled_cache is not None:
            self.core.set_property({"CACHE_DIR": str(compiled_cache)})
        self.model = self.core.read_model(str(path))
        self.threads = threads
        self.config = {"PERFORMANCE_HINT": "LATENCY", "NUM_STREAMS": 1,
                       "INFERENCE_PRECISION_HINT": inference_precision}
        self.compiled: dict[tuple, object] = {}

    def _request(self, shapes: tuple) -> object:
        # threads None: torch's at the call, so that the loop's two-thread layout (one torch thread in the network
        # thread while the tracker thread works: dfvo/inference/loop.py) runs the network on one core too
        threads = max(1, int(torch.get_num_threads() if self.threads is None else self.threads))
        request = self.compiled.get((shapes, threads))
        if request is None:
            model = self.model.clone()
            model.reshape({i: list(s) for i, s in enumerate(shapes)})
            config = {**self.config, "INFERENCE_NUM_THREADS": threads}
            request = self.core.compile_model(model, "CPU", config).create_infer_request()
            self.compiled[(shapes, threads)] = request
        return request

    def __call__(self, *inputs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        arrays = [_numpy(t) for t in inputs]
        request = self._request(tuple(a.shape for a in arrays))
        request.infer(arrays)
        return tuple(torch.from_numpy(np.array(request.get_output_tensor(i).data))
                     for i in range(len(request.model_outputs)))


def build_engine(kind: str, path: str | Path, threads: int | None = None, precision: str = "fp32") -> Engine:
    """The engine of runtime ``kind`` (``onnxruntime`` | ``openvino``) for the ONNX model ``path``; ``threads``
    None: torch's number of threads (ONNX Runtime: now; OpenVINO: at each call); ``precision`` ``fp32`` or ``bf16``
    (openvino; see :func:`check_precision`)."""
    if kind == "onnxruntime":
        return OnnxRuntimeEngine(path, torch.get_num_threads() if threads is None else threads)
    if kind == "openvino":
        return OpenVinoEngine(path, threads, PRECISIONS[precision], Path(path).parent / "openvino_compiled")
    raise ValueError(f"runtime {kind!r}; expected 'onnxruntime' or 'openvino'")
