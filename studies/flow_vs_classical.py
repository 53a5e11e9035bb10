"""Learned vs classical flow through the same tracker and the same depth: the figure issue 13 is judged by.

For every case (KITTI odometry 06 with its ground truth; held-out synthetic worlds of each scenario, seeds >= 1000,
never trained on) and every flow (below), the sequence runs through the inference loop
(:func:`dfvo.inference.loop.track_sequence`, the config ``infer.py`` composes: default tracker, 640x192, the shipped
depth network; on synthetic worlds also the true depth, ``--depths network,oracle``). Flows (``--flows``):

    - ``network``: the flow network with the refinement ``infer.py`` applies by default (``flow.refine``);
    - ``network_raw``: the network alone (``flow.refine.iterations=0``);
    - ``dis``: OpenCV's DIS (``flow=dis``, medium preset), the classical baseline;
    - ``network_pyramid``: the network refined coarse to fine at the selection's candidates
      (:mod:`dfvo.matching.pyramid_refinement`, settings ``--pyramid key=value ...``); more settings side by side
      with ``--variant NAME:key=value;key=value`` (each a flow named ``network_pyramid[NAME]``);
    - ``network_both`` (only when named in ``--flows``): the default refinement, then the pyramid's at its
      candidates (dense consistent pixels for the scale, accurate corners for the geometry).

Per run: RPE (m, deg) and ATE (m) as run and with every relative translation rescaled to its true length (what the
flow and geometry did, scale removed; as ``studies/error_decomposition.py``), per-frame translation-direction
and rotation errors (median/mean/max, degrees), the predicted / true translation length ratio (median, std: the
scale's error), the Sampson distance of the tracker's selected correspondences
under the true relative pose (pixels: median, p90, share above 1 px; pairs with < 0.1 m true translation skipped),
the trackers used (E / PnP / constant motion) and flow milliseconds per frame (network and refinement; wall time
and this thread's CPU time — the CPU is shared, wall time includes waiting for it). ``--kitti-steps 1,2,3`` adds the
same KITTI frames taken every 2nd and 3rd frame (2.4 and 3.6 m a frame on 06: highway-speed image motion on a road
with ground truth; cases ``kitti06_step2``, ``kitti06_step3``). Prints one JSON object (also
written to ``--out``). The network, its raw flow and the depth of a case are computed once and shared by its runs.
``--quick`` checks the whole path in a few minutes (KITTI frames 0-10, one drive and one highway world of 8 frames,
network depth only); its numbers are too few frames to compare flows by.

    python studies/flow_vs_classical.py --out /work/runs/flow_vs_classical_before.json    # ~30 min on 2 cores
    python studies/flow_vs_classical.py --quick --out /tmp/flow_vs_classical_quick.json   # plumbing, a few min
    python studies/flow_vs_classical.py --checkpoint /work/runs/flow_v2/weights.safetensors --skip-synthetic
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dfvo.eval import evaluate_trajectory
from dfvo.eval.epipolar import fundamental_from_pose
from dfvo.eval.error_decomposition import relative, scale_free
from dfvo.geometry.two_view import sampson_sq
from dfvo.inference.config import typed
from dfvo.inference.frames import build_sequence
from dfvo.inference.loop import track_sequence
from dfvo.inference.timing import StageTimer
from dfvo.matching.flow_refinement import refine_consecutive
from dfvo.matching.pyramid_refinement import PyramidRefinementConfig, refine_pyramid
from dfvo.sources import build_depth_source
from dfvo.sources.dis import DISFlow
from dfvo.sources.networks import NetworkFlow
from dfvo.synthetic import held_out_worlds
from dfvo.tracking import VisualOdometry

FLOWS = ("network", "network_raw", "dis", "network_pyramid")
EXTRA_FLOWS = ("network_both",)  # only when named in --flows


def compose_infer(overrides: list[str]) -> Any:
    """The typed config ``infer.py`` would run with these overrides."""
    from hydra import compose, initialize_config_module

    from dfvo.inference.config import register_configs

    register_configs()
    with initialize_config_module("dfvo.conf.infer", version_base="1.3"):
        return typed(compose("infer", overrides=overrides))


class Clock:
    """Wall and CPU (this thread) seconds of named stages."""

    def __init__(self) -> None:
        self.wall: dict[str, float] = {}
        self.cpu: dict[str, float] = {}

    def run(self, name: str, fn: Any, *args: Any) -> Any:
        w, c = time.perf_counter(), time.thread_time()
        out = fn(*args)
        self.wall[name] = self.wall.get(name, 0.0) + time.perf_counter() - w
        self.cpu[name] = self.cpu.get(name, 0.0) + time.thread_time() - c
        return out


class CaseFlow:
    """A flow source of one case: the base flow of each batch computed once (cached by frame indices), then the
    run's refinement; stage times in ``clock`` (the base flow's counted once per run, cached or not)."""

    def __init__(self, base: Any, cache: dict, base_clock: Clock, refine: Any = None) -> None:
        self.base, self.cache, self.base_clock, self.refine = base, cache, base_clock, refine
        self.name = getattr(base, "name", "flow")
        self.clock = Clock()

    def __call__(self, prev: torch.Tensor, cur: torch.Tensor, indices: list[int] | None = None
                 ) -> tuple[torch.Tensor, torch.Tensor]:
        key = tuple(indices)
        if key not in self.cache:
            self.cache[key] = self.base_clock.run(key, self.base, prev, cur, indices)
        for d, src in ((self.clock.wall, self.base_clock.wall), (self.clock.cpu, self.base_clock.cpu)):
            d["flow"] = d.get("flow", 0.0) + src[key]
        fwd, bwd = self.cache[key]
        if self.refine is None:
            return fwd, bwd
        consecutive = prev.shape[0] == 1 or torch.equal(prev[1:], cur[:-1])
        if not consecutive:
            raise ValueError("flow_vs_classical: the loop's pairs are not consecutive frames")
        return self.clock.run("refine", self.refine, torch.cat([prev, cur[-1:]]), fwd, bwd)


class CaseDepth:
    """The depth source of one case, each batch computed once."""

    def __init__(self, base: Any) -> None:
        self.base, self.cache, self.name = base, {}, base.name

    def __call__(self, images: torch.Tensor, indices: list[int] | None = None) -> torch.Tensor:
        key = tuple(indices)
        if key not in self.cache:
            self.cache[key] = self.base(images, indices)
        return self.cache[key]


def _stats(x: np.ndarray, digits: int = 3) -> dict[str, float | None]:
    if len(x) == 0:
        return {"median": None, "mean": None, "max": None}
    return {"median": round(float(np.median(x)), digits), "mean": round(float(np.mean(x)), digits),
            "max": round(float(np.max(x)), digits)}


def trajectory_metrics(gt: np.ndarray, pred: np.ndarray, per_frame: bool = False) -> dict[str, Any]:
    """RPE/ATE as run and with true lengths; per-frame direction and rotation errors (degrees), and with
    ``per_frame`` each frame's (direction error (NaN when still), rotation error, length ratio)."""
    rg, rp = relative(gt), relative(pred)
    true_lengths, moving, direction, ratio = scale_free(gt, pred)
    dR = np.einsum("nji,njk->nik", rg[:, :3, :3], rp[:, :3, :3])
    rotation = np.degrees(np.arccos(np.clip((np.trace(dR, axis1=1, axis2=2) - 1) / 2, -1.0, 1.0)))

    def m(traj: np.ndarray) -> dict[str, float]:
        r = evaluate_trajectory(gt, traj, align="6dof")
        return {"rpe_m": round(r["rpe_m"], 4), "rpe_deg": round(r["rpe_deg"], 4), "ate_m": round(r["ate_m"], 4)}

    extra = {}
    if per_frame:
        d_all = np.full(len(rg), np.nan)
        d_all[moving] = direction
        r_all = np.full(len(rg), np.nan)
        r_all[moving] = ratio
        extra["per_frame"] = {"direction_deg": [round(float(v), 3) for v in d_all],
                              "rotation_deg": [round(float(v), 4) for v in rotation],
                              "length_ratio": [round(float(v), 3) for v in r_all]}
    return {**extra, "as_run": m(pred), "true_lengths": m(true_lengths), "direction_error_deg": _stats(direction),
            "rotation_error_deg": _stats(rotation, 4),
            "length_ratio": {"median": round(float(np.median(ratio)), 4) if len(ratio) else None,
                             "std": round(float(np.std(ratio)), 4) if len(ratio) else None}}


def epipolar_errors(records: list[Any], gt: np.ndarray, K: np.ndarray) -> dict[str, Any]:
    """Sampson distance (px) of each frame's selected correspondences under the true relative pose."""
    dists, inlier_dists = [], []
    for rec in records:
        m = rec.result.matches
        T_prev_cur = np.linalg.inv(gt[rec.index - 1]) @ gt[rec.index]
        if m is None or len(m.pts_prev) == 0 or np.linalg.norm(T_prev_cur[:3, 3]) < 0.1:
            continue
        F = torch.from_numpy(fundamental_from_pose(T_prev_cur, K))[None, None]
        d = sampson_sq(F, m.pts_prev.double()[None].cpu(), m.pts_cur.double()[None].cpu())[0, 0].sqrt().numpy()
        dists.append(d)
        if m.inliers is not None:
            inlier_dists.append(d[m.inliers.cpu().numpy().astype(bool)])
    d = np.concatenate(dists) if dists else np.zeros(0)
    di = np.concatenate(inlier_dists) if inlier_dists else np.zeros(0)
    return {"selected": {"median": round(float(np.median(d)), 4) if len(d) else None,
                         "p90": round(float(np.quantile(d, 0.9)), 4) if len(d) else None,
                         "over_1px": round(float((d > 1).mean()), 4) if len(d) else None,
                         "per_frame": round(len(d) / max(len(dists), 1), 1)},
            "inliers_median": round(float(np.median(di)), 4) if len(di) else None, "frames": len(dists)}


def run_case(name: str, overrides: list[str], flows: list[str], depths: list[str], args: argparse.Namespace,
             pyramids: dict[str, PyramidRefinementConfig]) -> dict[str, Any]:
    cfg = compose_infer(overrides)
    seq = build_sequence(cfg.data, cfg.seq, cfg.img_res)
    frames: dict[int, torch.Tensor] = {}
    load = seq.load
    seq.load = lambda i: frames[i] if i in frames else frames.setdefault(i, load(i))  # decode/render once
    gt = seq.poses
    K = seq.K.double().numpy()
    net = NetworkFlow(args.checkpoint, input_size=args.input_size) if any(f.startswith("network") for f in flows) \
        else None
    bases = {"network": net, "dis": DISFlow("medium") if "dis" in flows else None}
    caches: dict[str, tuple[dict, Clock]] = {k: ({}, Clock()) for k in bases}
    refiners = {"network": (lambda im, f, b: refine_consecutive(im, f, b, cfg.flow.refine))
                if cfg.flow.refine.iterations > 0 else None,
                "network_raw": None, "dis": None,
                **{flow: (lambda im, f, b, c=c: refine_pyramid(im, f, b, c)) for flow, c in pyramids.items()},
                "network_both": lambda im, f, b: refine_pyramid(im, *refine_consecutive(im, f, b, cfg.flow.refine),
                                                                pyramids["network_pyramid"])}
    out: dict[str, Any] = {"frames": seq.length, "overrides": overrides}
    for depth_kind in depths:
        dcfg = compose_infer(overrides + [f"depth={depth_kind}"]).depth
        depth = CaseDepth(build_depth_source(dcfg, seq.world))
        rows = {}
        for flow in flows:
            base = "dis" if flow == "dis" else "network"  # network, network_raw, network_pyramid[...]
            src = CaseFlow(bases[base], *caches[base], refine=refiners[flow])
            vo = VisualOdometry(cfg.tracker)
            start = time.perf_counter()
            records = list(track_sequence(seq, src, depth, vo, refine=None, batch_size=cfg.batch_size,
                                          timer=StageTimer(), overlap=False))
            traj = np.stack([np.eye(4)] + [r.result.T_w_cur.detach().cpu().double().numpy() for r in records])
            used = [str(r.result.diagnostics.tracker.value) for r in records]
            n = len(records)
            ms = {f"{k}_ms": round(1000 * v / n, 1) for k, v in src.clock.wall.items()}
            ms.update({f"{k}_cpu_ms": round(1000 * v / n, 1) for k, v in src.clock.cpu.items()})
            ms["total_ms"] = round(sum(v for k, v in ms.items() if k.endswith("_ms") and "cpu" not in k), 1)
            ms["total_cpu_ms"] = round(sum(v for k, v in ms.items() if k.endswith("_cpu_ms")), 1)
            metrics = trajectory_metrics(gt, traj, args.per_frame)
            if args.per_frame:
                metrics["per_frame"]["tracker"] = used
                metrics["per_frame"]["correspondences"] = [r.result.diagnostics.num_correspondences for r in records]
            rows[flow] = {**metrics, "epipolar_px": epipolar_errors(records, gt, K),
                          "trackers": {t: used.count(t) for t in ("E", "PnP", "constant_motion")},
                          "flow_ms_per_frame": ms, "run_seconds": round(time.perf_counter() - start, 1)}
            print(json.dumps({"case": name, "depth": depth_kind, "flow": flow,
                              "rpe_true_lengths_m": rows[flow]["true_lengths"]["rpe_m"],
                              "rpe_m": rows[flow]["as_run"]["rpe_m"], "trackers": rows[flow]["trackers"],
                              "epipolar_median_px": rows[flow]["epipolar_px"]["selected"]["median"], **ms}),
                  file=sys.stderr, flush=True)
        out[f"depth={depth_kind}"] = rows
    return out


def summary(cases: dict[str, Any], flows: list[str]) -> dict[str, Any]:
    """True-length RPE per flow: KITTI, and per synthetic scenario the mean over its worlds (depth=network and
    depth=oracle)."""
    out: dict[str, Any] = {}
    for depth in ("depth=network", "depth=oracle"):
        table: dict[str, dict[str, list[float]]] = {}
        for name, case in cases.items():
            if depth not in case:
                continue
            group = name if name.startswith("kitti") else name.split("_s")[0]
            for flow in flows:
                row = case[depth][flow]
                table.setdefault(group, {}).setdefault(flow, []).append(row["true_lengths"]["rpe_m"])
        if table:
            out[depth] = {g: {f: round(float(np.mean(v)), 4) for f, v in fl.items()} for g, fl in table.items()}
    return out


def _pyramid(settings: list[str]) -> PyramidRefinementConfig:
    """A :class:`PyramidRefinementConfig` from ``key=value`` strings (values as JSON)."""
    return PyramidRefinementConfig(**{k: json.loads(v) for k, v in (kv.split("=", 1) for kv in settings)})


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--kitti-root", default=str(Path(__file__).resolve().parents[2] / "shared/data/kitti_odom"))
    p.add_argument("--seq", default="06")
    p.add_argument("--kitti-frames", type=int, default=None, help="only KITTI frames [0, N) (default: all)")
    p.add_argument("--kitti-steps", default="1", help="KITTI frame steps, one case each (e.g. 1,2,3: every 2nd and "
                   "3rd frame of the same road doubles and triples the motion per frame, a highway-speed stand-in)")
    p.add_argument("--scenarios", default="drive,city,straight,highway")
    p.add_argument("--per-scenario", type=int, default=1, help="held-out worlds per scenario (seeds 1000, 1001..)")
    p.add_argument("--synthetic-frames", type=int, default=40)
    p.add_argument("--flows", default=",".join(FLOWS))
    p.add_argument("--depths", default="network,oracle", help="depths on synthetic worlds (KITTI: network)")
    p.add_argument("--checkpoint", default="checkpoints/flow.safetensors")
    p.add_argument("--input-size", default=None, help="H,W the network runs at (default: checkpoint metadata)")
    p.add_argument("--pyramid", nargs="*", default=[], help="PyramidRefinementConfig settings key=value")
    p.add_argument("--variant", action="append", default=[], help="NAME:key=value;key=value (repeatable)")
    p.add_argument("--overrides", nargs="*", default=[], help="further infer.py overrides for every case, e.g. "
                   "tracker.gate.enabled=false")
    p.add_argument("--per-frame", action="store_true", help="also each frame's errors, tracker and correspondences")
    p.add_argument("--skip-kitti", action="store_true")
    p.add_argument("--skip-synthetic", action="store_true")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", default=None, help="also write the JSON here")
    p.add_argument("--quick", action="store_true", help="a few minutes: --kitti-frames 11 --scenarios drive,highway "
                   "--synthetic-frames 8 --depths network")
    args = p.parse_args()
    if args.quick:
        args.kitti_frames, args.scenarios, args.synthetic_frames, args.depths = 11, "drive,highway", 8, "network"
    torch.set_num_threads(args.threads)
    from dfvo.sources import find_checkpoint

    args.checkpoint = str(find_checkpoint(args.checkpoint, "--checkpoint"))
    args.input_size = None if args.input_size is None else [int(v) for v in args.input_size.split(",")]
    pyramids = {"network_pyramid": _pyramid(args.pyramid)}
    for spec in args.variant:
        name, _, settings = spec.partition(":")
        pyramids[f"network_pyramid[{name}]"] = _pyramid([kv for kv in settings.split(";") if kv])
    flows = args.flows.split(",") + [f for f in pyramids if f != "network_pyramid"]
    unknown = [f for f in flows if f not in FLOWS + EXTRA_FLOWS and f not in pyramids]
    if unknown:
        raise SystemExit(f"--flows: unknown {unknown}; expected some of {FLOWS + EXTRA_FLOWS}")
    common = ["progress=false", f"num_threads={args.threads}", *args.overrides]
    cases: dict[str, Any] = {}
    started = time.time()
    if not args.skip_kitti:
        first = [] if args.kitti_frames is None else ["data.start=0", f"data.end={args.kitti_frames}"]
        for step in (int(v) for v in args.kitti_steps.split(",")):
            name = f"kitti{args.seq}" + ("" if step == 1 else f"_step{step}")
            cases[name] = run_case(name, ["data=kitti_odom", f"data.root={args.kitti_root}", f"seq={args.seq}",
                                          *first, f"data.step={step}", *common], flows, ["network"], args, pyramids)
    if not args.skip_synthetic:
        for world in held_out_worlds(args.scenarios.split(","), args.per_scenario):
            speed = "null" if world.speed is None else (f"{world.speed}" if isinstance(world.speed, float)
                                                         else f"[{world.speed[0]},{world.speed[1]}]")
            ov = ["data=synthetic", f"seq={world.scenario}", f"data.seed={world.seed}",
                  f"data.num_frames={args.synthetic_frames}", f"data.speed={speed}", *common]
            cases[world.name] = run_case(world.name, ov, flows, args.depths.split(","), args, pyramids)
    result = {"machine": f"{platform.machine()}, {os.cpu_count()} cores, torch threads {args.threads}, "
                         f"load average at the end {os.getloadavg()[0]:.1f}",
              "date": time.strftime("%Y-%m-%d %H:%M"), "quick": args.quick, "command": " ".join(sys.argv),
              "minutes": round((time.time() - started) / 60, 1),
              "checkpoint": args.checkpoint, "pyramid": {k: vars(v) for k, v in pyramids.items()}, "flows": flows,
              "summary_true_length_rpe_m": summary(cases, flows), "cases": cases}
    text = json.dumps(result, indent=1)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(text)
    print(text)


if __name__ == "__main__":
    main()
