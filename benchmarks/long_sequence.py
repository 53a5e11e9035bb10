"""Long sequences: memory and time per frame stay flat over a 2000-frame run of ``infer.py``, and its outputs are
complete.

Runs ``python infer.py`` (a child process, exactly as a user would) on a synthetic drive of ``--frames`` frames and
samples, every ``--every`` seconds, the child's resident memory (``/proc/PID/status`` VmRSS) and how many frames it
has finished (the rows of its ``frames.csv``, flushed once per frame). Prints one JSON object:

    - ``rss_mb``: at frame ``--from-frame`` (100), at the end, the growth between them (``growth_ok``: at most
      ``--max-growth-mb``, 100 MB), and the peak;
    - ``ms_per_frame``: wall time and the child's CPU time (user + system, all threads: ``/proc/PID/stat``) per
      frame over the first and the last quarter of the frames and their ratios (``flat_ok`` when the last quarter's
      CPU time is at most ``--max-slowdown`` (1.25) times the first's: on a shared machine the wall time follows the
      neighbours' load, the CPU time the work), and each stage's mean wall ms/frame in the first and last quarter
      from ``frames.csv`` (t_flow, t_refine, t_depth, t_tracker);
    - ``outputs``: the pose file's lines, ``frames.csv``'s rows, ``summary.json``'s ``frames_written`` and whether
      ``metrics.json`` exists (``complete``: all equal to ``--frames``);
    - the machine's load average before and after (on a shared machine the wall times follow the neighbours; the
      CPU times and the memory check do not).

Defaults: 2000 frames at 96x320 with the oracle flow and depth (their cost is the synthetic renderer's, so the run
measures the loop, the tracker and the outputs, not the networks) and one torch thread. On the 2-core reference CPU
(shared, load 3-5) 1101 frames took 885 s (``docs/speed.md``), so 2000 take about half an hour; run it in the
background:

    nohup python benchmarks/long_sequence.py > long_sequence.json 2> long_sequence.log &
    python benchmarks/long_sequence.py --frames 300 --sources network     # the networks instead (slower per frame)
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _rss_mb(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


def _cpu_s(pid: int) -> float | None:
    """CPU seconds (user + system, all threads) the process has used so far, from ``/proc/PID/stat``."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime, stime (fields 14, 15)


def _rows(path: Path) -> int:
    """Finished frames: data rows of frames.csv after its frame-0 row (0 while it does not exist)."""
    try:
        with path.open() as f:
            return max(0, sum(1 for _ in f) - 2)
    except OSError:
        return 0


def _stage_means(rows: list[dict[str, str]]) -> dict[str, float]:
    out = {}
    for key in ("t_flow", "t_refine", "t_depth", "t_tracker"):
        vals = [float(r[key]) for r in rows if r.get(key) not in (None, "")]
        if vals:
            out[key] = round(1000.0 * sum(vals) / len(vals), 2)
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=2000)
    p.add_argument("--height", type=int, default=96)
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--sources", choices=["oracle", "network"], default="oracle")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--every", type=float, default=1.0, help="sampling period, seconds")
    p.add_argument("--from-frame", type=int, default=100)
    p.add_argument("--max-growth-mb", type=float, default=100.0)
    p.add_argument("--max-slowdown", type=float, default=1.25)
    p.add_argument("--out-dir", default=None, help="keep the run's outputs here (default: a temporary folder)")
    p.add_argument("--overrides", nargs="*", default=[])
    args = p.parse_args()
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(args.out_dir) if args.out_dir else Path(tmp) / "out"
        cmd = [sys.executable, str(REPO / "infer.py"), "data=synthetic", f"data.num_frames={args.frames}",
               f"img_res.height={args.height}", f"img_res.width={args.width}", f"out_dir={out}", "progress=false",
               f"num_threads={args.threads}"]
        cmd += ["flow=oracle", "depth=oracle"] if args.sources == "oracle" else ["flow=network", "depth=network"]
        cmd += list(args.overrides)
        env = dict(os.environ, OMP_NUM_THREADS=str(args.threads))
        start = time.perf_counter()
        child = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                 text=True)
        samples: list[tuple[float, int, float, float]] = []  # (seconds, frames finished, rss MB, CPU seconds)
        while child.poll() is None:
            rss, cpu = _rss_mb(child.pid), _cpu_s(child.pid)
            if rss is not None and cpu is not None:
                samples.append((time.perf_counter() - start, _rows(out / "frames.csv"), rss, cpu))
            time.sleep(args.every)
        stderr = child.stderr.read() if child.stderr else ""
        wall = time.perf_counter() - start
        report = _report(args, out, samples, wall, child.returncode, stderr)
    report.update(command=" ".join(cmd[1:]), load_avg_before=round(load_before, 2),
                  load_avg_after=round(os.getloadavg()[0], 2))
    print(json.dumps(report, indent=2))
    sys.exit(0 if report.get("ok") else 1)


def _at(samples: list[tuple[float, int, float, float]], frame: int) -> tuple[float, int, float, float] | None:
    """The first sample with at least ``frame`` frames finished."""
    return next((s for s in samples if s[1] >= frame), None)


def _report(args: argparse.Namespace, out: Path, samples: list[tuple[float, int, float, float]], wall: float,
            returncode: int, stderr: str) -> dict:
    n = args.frames - 1  # tracked frames (frame 0 is the identity)
    rows = list(csv.DictReader((out / "frames.csv").open()))[1:] if (out / "frames.csv").is_file() else []
    pose_files = [f for f in out.glob("*.txt")]
    summary = json.loads((out / "summary.json").read_text()) if (out / "summary.json").is_file() else {}
    outputs = {
        "pose_lines": len(pose_files[0].read_text().splitlines()) if pose_files else 0,
        "frames_csv_rows": len(rows) + 1 if rows else 0,
        "frames_written": summary.get("frames_written"),
        "metrics_json": (out / "metrics.json").is_file(),
    }
    outputs["complete"] = (outputs["pose_lines"] == args.frames and outputs["frames_csv_rows"] == args.frames
                           and outputs["frames_written"] == args.frames and outputs["metrics_json"])
    first, last = _at(samples, args.from_frame), _at(samples, n)  # last: all frames tracked (before plotting)
    q1, q3 = _at(samples, n // 4), _at(samples, 3 * n // 4)
    t_start = _at(samples, 1)
    rss = {
        "at_frame": first[1] if first else None,
        "at_frame_mb": round(first[2], 1) if first else None,
        "end_frame": last[1] if last else None,
        "end_mb": round(last[2], 1) if last else None,
        "peak_mb": round(max(s[2] for s in samples), 1) if samples else None,  # (includes the final plots)
    }
    rss["growth_mb"] = round(last[2] - first[2], 1) if first and last else None
    rss["growth_ok"] = rss["growth_mb"] is not None and rss["growth_mb"] <= args.max_growth_mb
    timing: dict = {}
    if t_start and q1 and q3 and last and q1[1] > t_start[1] and last[1] > q3[1]:
        for key, col in (("", 0), ("cpu_", 3)):  # wall time, and the child's CPU time (what neighbours don't change)
            timing[f"{key}first_quarter"] = round(1000.0 * (q1[col] - t_start[col]) / (q1[1] - t_start[1]), 1)
            timing[f"{key}last_quarter"] = round(1000.0 * (last[col] - q3[col]) / (last[1] - q3[1]), 1)
            timing[f"{key}ratio"] = round(timing[f"{key}last_quarter"] / timing[f"{key}first_quarter"], 3)
        timing["flat_ok"] = timing["cpu_ratio"] <= args.max_slowdown
    if rows:
        timing["stages_first_quarter"] = _stage_means(rows[: n // 4])
        timing["stages_last_quarter"] = _stage_means(rows[-(n // 4):])
    return {
        "frames": args.frames, "resolution": [args.height, args.width], "sources": args.sources,
        "threads": args.threads, "returncode": returncode, "wall_s": round(wall, 1),
        "fps": summary.get("fps"), "rss_mb": rss, "ms_per_frame": timing, "outputs": outputs,
        "samples": len(samples), "stderr_tail": stderr[-1500:] if returncode else None,
        "ok": bool(returncode == 0 and outputs["complete"] and rss["growth_ok"] and timing.get("flat_ok")),
    }


if __name__ == "__main__":
    main()
