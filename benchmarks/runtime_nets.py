"""Per-network speed and agreement of the CPU runtimes: PyTorch eager against its torch-side options, ONNX Runtime
and OpenVINO (fp32, bf16 where the CPU has it, int8 calibrated on KITTI raw frames).

For the flow network (``FlowNet.forward_backward``, B pairs) and the depth network (``DepthNet.depth``, B frames) at
the shipped input size (the checkpoints' metadata, 96x320), batch ``--batch`` (the loop's default 4):

- ``ms``: milliseconds per call, median of ``--repeats`` rounds, per torch/runtime thread count (``--threads``);
  every round runs each candidate once, in turn, so all candidates see the same machine load; ``ratio``: the median
  over rounds of the candidate's time over eager's in the same round (the fair number on a shared machine).
- agreement with eager on KITTI odometry 06 and 07 frames at the working size 640x192 (``--eval-pairs`` pairs each):
  flow end-point difference in pixels of 640x192 (mean, p99, max over pixels), depth relative difference
  ``|d - d_eager| / d_eager`` (mean, p99, max).

int8: static quantisation (ONNX Runtime's ``quantize_static``, QDQ, per-channel int8 weights, int8 activations, the
convolutions only) calibrated on ``--calib-frames`` KITTI raw frames (drive 2011_09_26_0001, a different drive from
the odometry sequences it is evaluated on); OpenVINO runs the same QDQ model (its int8 kernels).

Usage:
    OMP_NUM_THREADS=2 python benchmarks/runtime_nets.py --kitti-odom ../shared/data/kitti_odom \
        --kitti-raw ../shared/data/kitti_raw [--threads 1 2] [--repeats 9] [--only flow|depth] [--out FILE]
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import platform
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from dfvo.inference.config import ImgResConfig, KittiOdomDataConfig, KittiRawDataConfig
from dfvo.inference.frames import build_sequence
from dfvo.io.checkpoint import find_checkpoint
from dfvo.sources.networks import NetworkDepth, NetworkFlow, _resize_flow

CPU_FLAGS = ("avx2", "avx512f", "avx512_vnni", "avx_vnni", "avx512_bf16", "amx_bf16", "amx_int8")


def cpu_flags() -> dict[str, bool]:
    """The instruction-set flags that decide bf16/int8 kernels, from /proc/cpuinfo (never assumed)."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return {f: False for f in CPU_FLAGS}
    line = next((ln for ln in text.splitlines() if ln.startswith("flags")), "")
    have = set(line.split(":", 1)[-1].split())
    return {f: f in have for f in CPU_FLAGS}


def frames(root: str, kind: str, seq: str, count: int) -> torch.Tensor:
    """(count,3,192,640) frames of a KITTI sequence at the pipeline's working size (as infer.py loads them)."""
    cfg = (KittiOdomDataConfig(root=root, seq=seq, end=count) if kind == "odom"
           else KittiRawDataConfig(root=root, seq=seq, end=count))
    s = build_sequence(cfg, None, ImgResConfig())
    return torch.stack([s.image(i) for i in range(min(count, s.length))])


def timed(fn: Callable[[], object]) -> float:
    start = time.perf_counter()
    fn()
    return 1000.0 * (time.perf_counter() - start)


def quantize_int8(fp32: Path, out: Path, feeds: list[dict[str, np.ndarray]]) -> Path:
    """Static int8 QDQ model of ``fp32`` calibrated on ``feeds`` (convolutions only; per-channel weights)."""
    from onnxruntime.quantization import CalibrationDataReader, QuantFormat, QuantType, quantize_static
    from onnxruntime.quantization.shape_inference import quant_pre_process

    class Reader(CalibrationDataReader):
        def __init__(self) -> None:
            self.it = iter(feeds)

        def get_next(self) -> dict[str, np.ndarray] | None:
            return next(self.it, None)

    pre = out.with_name(out.stem + "_pre.onnx")
    quant_pre_process(str(fp32), str(pre), skip_symbolic_shape=True)
    quantize_static(str(pre), str(out), Reader(), quant_format=QuantFormat.QDQ, per_channel=True,
                    activation_type=QuantType.QInt8, weight_type=QuantType.QInt8, op_types_to_quantize=["Conv"],
                    extra_options={"ActivationSymmetric": True})
    return out


class Candidates:
    """The runnable variants of one network at one thread count: name -> callable of the network's inputs."""

    def __init__(self, what: str, source: NetworkFlow | NetworkDepth, onnx_fp32: Path, onnx_int8: Path | None,
                 threads: int, flags: dict[str, bool], example: tuple[torch.Tensor, ...], compile_: bool) -> None:
        from dfvo.sources.runtime.engines import OnnxRuntimeEngine, OpenVinoEngine

        torch.set_num_threads(threads)
        self.fns: dict[str, Callable[..., tuple[torch.Tensor, ...]]] = {}
        model = source.model
        if what == "flow":
            def eager(*x: torch.Tensor) -> tuple[torch.Tensor, ...]:
                with torch.no_grad():
                    return tuple(model.forward_backward(*x))
        else:
            def eager(*x: torch.Tensor) -> tuple[torch.Tensor, ...]:
                with torch.no_grad():
                    return (model.depth(*x),)
        self.fns["torch"] = eager
        if what == "flow":
            cl = copy.deepcopy(model).eval().to(memory_format=torch.channels_last)

            def channels_last(*x: torch.Tensor) -> tuple[torch.Tensor, ...]:
                with torch.no_grad():
                    return tuple(cl.forward_backward(*(t.contiguous(memory_format=torch.channels_last) for t in x)))
            self.fns["torch_channels_last"] = channels_last
        if flags["avx512_bf16"] or flags["amx_bf16"]:
            def bf16(*x: torch.Tensor) -> tuple[torch.Tensor, ...]:
                with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
                    return tuple(o.float() for o in eager(*x))
            self.fns["torch_bf16"] = bf16
        from dfvo.sources.runtime.export import DepthGraph, FlowGraph
        graph = (FlowGraph(model) if what == "flow" else DepthGraph(model)).eval()
        with torch.no_grad():
            traced = torch.jit.freeze(torch.jit.trace(graph, example, check_trace=False))
            traced = torch.jit.optimize_for_inference(traced)

        def jit(*x: torch.Tensor) -> tuple[torch.Tensor, ...]:
            with torch.no_grad():
                out = traced(*x)
                return tuple(out) if isinstance(out, tuple | list) else (out,)
        self.fns["torch_jit"] = jit
        if compile_:
            compiled = torch.compile(graph, dynamic=False)

            def comp(*x: torch.Tensor) -> tuple[torch.Tensor, ...]:
                with torch.no_grad():
                    out = compiled(*x)
                    return tuple(out) if isinstance(out, tuple | list) else (out,)
            self.fns["torch_compile"] = comp
        self.fns["onnxruntime"] = OnnxRuntimeEngine(onnx_fp32, threads)
        self.fns["openvino"] = OpenVinoEngine(onnx_fp32, threads)
        if flags["avx512_bf16"] or flags["amx_bf16"]:
            self.fns["openvino_bf16"] = OpenVinoEngine(onnx_fp32, threads, inference_precision="bf16")
        if onnx_int8 is not None:
            self.fns["onnxruntime_int8"] = OnnxRuntimeEngine(onnx_int8, threads)
            self.fns["openvino_int8"] = OpenVinoEngine(onnx_int8, threads)


def speed(c: Candidates, example: tuple[torch.Tensor, ...], repeats: int) -> dict[str, dict[str, float]]:
    """Interleaved rounds: ms per call (median) and the median per-round ratio to eager."""
    for fn in c.fns.values():  # warm-up (compiles, caches, first-touch allocations)
        fn(*example)
        fn(*example)
    times: dict[str, list[float]] = {k: [] for k in c.fns}
    for _ in range(repeats):
        for name, fn in c.fns.items():
            times[name].append(timed(lambda fn=fn: fn(*example)))
    base = times["torch"]
    return {name: {"ms": round(statistics.median(t), 2),
                   "ratio": round(statistics.median(x / b for x, b in zip(t, base)), 3)}
            for name, t in times.items()}


def agreement(what: str, c: Candidates, source: NetworkFlow | NetworkDepth, seqs: dict[str, torch.Tensor],
              batch: int) -> dict[str, dict[str, dict[str, float]]]:
    """Per candidate and sequence: flow end-point or depth relative difference to eager at 640x192."""
    out: dict[str, dict[str, dict[str, float]]] = {name: {} for name in c.fns if name != "torch"}
    for seq, imgs in seqs.items():
        diffs: dict[str, list[torch.Tensor]] = {name: [] for name in out}
        n = imgs.shape[0] - 1 if what == "flow" else imgs.shape[0]
        for first in range(0, n, batch):
            last = min(first + batch, n)
            if what == "flow":
                net_in = source.network_inputs(imgs[first:last], imgs[first + 1:last + 1])
            else:
                size = source.network_size(*(source.input_size or imgs.shape[-2:]))
                net_in = (torch.nn.functional.interpolate(imgs[first:last], size=size, mode="bilinear",
                                                          align_corners=False, antialias=True),)
            ref = c.fns["torch"](*net_in)
            for name in out:
                got = c.fns[name](*net_in)
                if what == "flow":
                    for r, g in zip(ref, got):
                        r, g = _resize_flow(r, tuple(imgs.shape[-2:])), _resize_flow(g.float(), tuple(imgs.shape[-2:]))
                        diffs[name].append((g - r).norm(dim=1).flatten())
                else:
                    diffs[name].append(((got[0].float() - ref[0]).abs() / ref[0]).flatten())
        for name, d in diffs.items():
            d = torch.cat(d)
            out[name][seq] = {"mean": round(d.mean().item(), 5), "p99": round(float(np.percentile(d.numpy(), 99)), 5),
                              "max": round(d.max().item(), 5)}
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--kitti-odom", required=True)
    p.add_argument("--kitti-raw", required=True)
    p.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    p.add_argument("--repeats", type=int, default=9)
    p.add_argument("--batch", type=int, default=4)
    p.add_argument("--eval-pairs", type=int, default=40, help="frame pairs of KITTI 06 and of 07 for agreement")
    p.add_argument("--calib-frames", type=int, default=40, help="KITTI raw frames for the int8 calibration")
    p.add_argument("--only", choices=["flow", "depth"], default=None)
    p.add_argument("--no-int8", action="store_true")
    p.add_argument("--compile", action="store_true", help="also torch.compile (inductor; slow to compile)")
    p.add_argument("--cache-dir", default=None)
    p.add_argument("--out", default=None)
    args = p.parse_args()
    from dfvo.sources.runtime.export import ExportSpec, exported_model

    flags = cpu_flags()
    seqs = {s: frames(args.kitti_odom, "odom", s, args.eval_pairs + 1) for s in ("06", "07")}
    calib = frames(args.kitti_raw, "raw", "2011_09_26_drive_0001_sync", args.calib_frames + 1)
    cache = Path(args.cache_dir) if args.cache_dir else Path(tempfile.mkdtemp(prefix="dfvo_rt_"))
    report: dict[str, object] = {"cpu_flags": flags, "machine": f"{platform.processor() or platform.machine()}, "
                                 f"{os.cpu_count()} cores", "load_avg_before": round(os.getloadavg()[0], 2),
                                 "batch": args.batch, "repeats": args.repeats, "networks": {}}
    for what in ("flow", "depth"):
        if args.only and what != args.only:
            continue
        torch.set_num_threads(max(args.threads))
        if what == "flow":
            source = NetworkFlow(find_checkpoint("checkpoints/flow.safetensors"))
            size = source.input_size
            spec = ExportSpec("flow", source.checkpoint, size, variant=source.variant)
            example = tuple(torch.rand(args.batch, 3, *size) for _ in range(2))
            feeds = []
            for k in range(calib.shape[0] - 1):
                a, b = source.network_inputs(calib[k:k + 1], calib[k + 1:k + 2])
                feeds.append({"img1": a.numpy(), "img2": b.numpy()})
        else:
            source = NetworkDepth(find_checkpoint("checkpoints/depth.safetensors"))
            size = source.network_size(*source.input_size)
            spec = ExportSpec("depth", source.checkpoint, size, min_depth=source.model.min_depth,
                              max_depth=source.model.max_depth)
            example = (torch.rand(args.batch, 3, *size),)
            feeds = [{"image": torch.nn.functional.interpolate(calib[k:k + 1], size=size, mode="bilinear",
                                                               align_corners=False, antialias=True).numpy()}
                     for k in range(calib.shape[0])]
        fp32 = exported_model(spec, lambda source=source: source.model, cache)
        int8 = None if args.no_int8 else quantize_int8(fp32, cache / f"{what}_int8.onnx", feeds)
        net: dict[str, object] = {"input_size": list(size), "speed": {}}
        for threads in args.threads:
            c = Candidates(what, source, fp32, int8, threads, flags, example, args.compile)
            net["speed"][str(threads)] = speed(c, example, args.repeats)
            if threads == max(args.threads):
                net["agreement"] = agreement(what, c, source, seqs, args.batch)
        report["networks"][what] = net
        print(json.dumps({what: net}), flush=True)
    report["load_avg_after"] = round(os.getloadavg()[0], 2)
    text = json.dumps(report, indent=2)
    if args.out:
        Path(args.out).write_text(text)
    print(text)


if __name__ == "__main__":
    main()
