"""Regenerate the measured-results tables of README.md and docs/results.md from the JSON that the runs wrote.

Every generated table sits between two marker comments in the Markdown files; the script replaces what is between
them and leaves the rest of the file alone, so rerunning it after new measurements refreshes every table::

    <!-- results:NAME -->
    | ... generated ... |
    <!-- /results:NAME -->

Tables (NAME, and the JSON it reads; ``BENCH`` = ``--bench`` folders, ``ABL`` = ``--ablations`` folder):

    headline    the end-to-end runs: ``BENCH/ROW.json`` (``benchmarks/infer_fps.py`` output, as
                ``benchmarks/run_all.sh`` names them: fps_kitti06, fps_kitti06_one_view_scale, ...) or an infer run
                folder ``BENCH/ROW/`` (its ``summary.json`` and ``metrics.json``); ``--run ROW=PATH`` points a row
                at any run folder or JSON file. Several ``--bench`` folders (repeated idle runs) give ranges.
    timing      milliseconds per frame and stage of the same rows.
    components  ``BENCH/{depth_net,flow_net,tracker,synthetic_render,eval_speed}.json`` (the component benchmarks).
    ablation_kitti06, ablation_synthetic_oracle, ablation_synthetic_network
                ``scripts/aggregate_ablation.py --reference --fallback`` on ``ABL/NAME/`` (``scripts/run_ablation.sh``
                output; ``--ablation NAME=PATH`` points a table at another folder).

Every table carries the date of its inputs (the ``date`` key of a JSON, else the file's modification time), the
machine (the ``machine`` key the benchmark scripts write, else ``--machine TEXT``, else "machine not recorded")
and the command that measures it. A table whose inputs are incomplete is kept as it is and the missing files are
listed (``--partial`` renders the rows that have data instead).

Usage:
    benchmarks/run_all.sh runs/bench                       # the headline, timing and component JSONs
    scripts/run_ablation.sh runs/ablation_kitti06 data=kitti_odom data.root=ROOT seq=06   # (and the other two)
    python scripts/results_tables.py                       # rewrites README.md and docs/results.md
    python scripts/results_tables.py --bench runs/bench --bench runs/bench2 --machine "2-core AMD EPYC, idle"
    python scripts/results_tables.py --run fps_kitti06=OUT/kitti06 --print   # show the tables, write nothing
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import re
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from dfvo.eval.ablation import load_runs
from dfvo.eval.ablation import table as ablation_table

REPO = Path(__file__).resolve().parents[1]

DEFAULT_FILES = (REPO / "README.md", REPO / "docs" / "results.md")
MARKER = re.compile(r"<!-- results:(?P<name>[a-z0-9_]+) -->\n(?P<body>.*?)<!-- /results:(?P=name) -->", re.DOTALL)


class MissingInput(Exception):
    """A table's inputs are absent or incomplete (the message lists what was expected)."""


# ------------------------------------------------------------------------------------------------ measurements
@dataclass
class Measured:
    """One JSON result: its content, where it came from, when and on what it was measured."""

    path: Path
    data: dict[str, Any]
    date: str
    machine: str


def _date(data: dict[str, Any], path: Path) -> str:
    if data.get("date"):
        return str(data["date"])[:10]
    return dt.datetime.fromtimestamp(path.stat().st_mtime).strftime("%Y-%m-%d")


def _machine(data: dict[str, Any], fallback: str) -> str:
    m = data.get("machine")
    load = data.get("load_avg")
    if isinstance(m, dict):
        parts = [str(m.get("cpu") or "")]
        if m.get("cores"):
            parts.append(f"{m['cores']} cores")
        if m.get("torch_threads") or data.get("torch_threads"):
            parts.append(f"{m.get('torch_threads') or data.get('torch_threads')} torch threads")
        load = m.get("load_avg_1min", load)
        text = ", ".join(p for p in parts if p)
    elif m:
        text = str(m)
        if data.get("torch_threads") and "thread" not in text:
            text += f", {data['torch_threads']} torch threads"
    else:
        return fallback
    if load is not None:
        text += f", load {float(load):.1f}"
    return text


def read_json(path: Path, machine: str) -> Measured:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise MissingInput(f"{path}: not readable as JSON ({err})") from None
    if not isinstance(data, dict):
        raise MissingInput(f"{path}: expected one JSON object")
    return Measured(path, data, _date(data, path), _machine(data, machine))


def read_run(path: Path, machine: str) -> Measured:
    """A run result: an infer run folder (``summary.json``, metrics inside or in ``metrics.json``) or a JSON file
    (``benchmarks/infer_fps.py`` output, or a ``summary.json``), normalised to the keys of ``infer_fps.py``."""
    if path.is_dir():
        path = path / "summary.json"
    if not path.is_file():
        raise MissingInput(f"{path}: no such file")
    m = read_json(path, machine)
    d = m.data
    metrics = d.get("metrics")
    if metrics is None and (path.parent / "metrics.json").is_file():
        metrics = json.loads((path.parent / "metrics.json").read_text())
    if metrics is not None:  # a summary.json: lift the metrics to the top level, as infer_fps.py prints them
        for key in ("rpe_m", "rpe_deg", "ate_m", "t_err_pct", "r_err_deg_per_100m"):
            d.setdefault(key, metrics.get(key))
    if "fps" not in d or "timing_ms_per_frame" not in d:
        raise MissingInput(f"{path}: expected an infer run's summary.json or benchmarks/infer_fps.py output "
                           "(keys fps, timing_ms_per_frame)")
    if d.get("fps_without_loading") is None and d.get("fps"):
        per_frame = 1000.0 / d["fps"] - d["timing_ms_per_frame"].get("load", 0.0)
        d["fps_without_loading"] = 1000.0 / per_frame if per_frame > 0 else None
    return m


# ------------------------------------------------------------------------------------------------- formatting
def num(x: float | None) -> str:
    """Three significant digits; scientific below 1e-3; '–' for missing values."""
    if x is None:
        return "–"
    x = float(x)
    if x != 0 and abs(x) < 1e-3:
        return f"{x:.1e}"
    return f"{x:.3g}"


def span(values: list[float | None], fmt: Callable[[float | None], str] = num) -> str:
    """One value, or ``min–max`` when repeated measurements differ after formatting."""
    present = [v for v in values if v is not None]
    if not present:
        return "–"
    lo, hi = fmt(min(present)), fmt(max(present))
    return lo if lo == hi else f"{lo}–{hi}"


def fps_fmt(x: float | None) -> str:
    return "–" if x is None else f"{x:.1f}"


def measured_on(records: list[Measured]) -> str:
    dates = sorted({r.date for r in records})
    machines = sorted({r.machine for r in records})
    return f"{', '.join(dates)}; {' / '.join(machines)}"


def markdown(head: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join(["---"] * len(head)) + "|"]
    lines += ["| " + " | ".join(c.replace("|", "\\|") for c in row) + " |" for row in rows]
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------------ the tables
@dataclass
class Target:
    """A goal a row is checked against: ``key`` of the run compared with ``value`` (``<=`` or ``>=``)."""

    label: str
    key: str
    op: str
    value: float

    def verdict(self, records: list[Measured]) -> str:
        values = [r.data.get(self.key) for r in records]
        if any(v is None for v in values):
            return f"{self.label}: –"
        ok = all(v <= self.value if self.op == "<=" else v >= self.value for v in values)
        return f"{self.label}: {'met' if ok else '**not met**'}"


@dataclass
class RunRow:
    name: str  # file/folder name under a --bench folder (benchmarks/run_all.sh's name)
    label: str
    command: str
    targets: list[Target] = field(default_factory=list)
    expect: dict[str, str] = field(default_factory=dict)  # settings a run folder's summary.json must show

    def check(self, record: Measured) -> None:
        """Warn when a run folder's recorded settings are not this row's (infer_fps.py JSON records none)."""
        if "choices" not in record.data:
            return
        settings = {**{k: str(v) for k, v in (record.data.get("overrides") or {}).items()},
                    **{k: str(v) for k, v in record.data["choices"].items()}}
        wrong = {k: settings.get(k) for k, v in self.expect.items() if settings.get(k) != v}
        if wrong:
            print(f"results:headline: {record.path} for row {self.name} has {wrong}, expected {self.expect}",
                  file=sys.stderr)


KITTI = "python infer.py data=kitti_odom data.root=ROOT seq=06"
HEADLINE_ROWS = [
    RunRow("fps_kitti06", "KITTI 06 frames 0–50, shipped networks (6-DoF alignment)", KITTI,
           [Target("RPE ≤ 0.04 m", "rpe_m", "<=", 0.04), Target("≥ 10 FPS", "fps", ">=", 10.0)],
           expect={"data": "kitti_odom"}),
    RunRow("fps_kitti06_per_frame_scale", "same, the paper's scale (earlier frame's depth, per frame, no camera "
           "height)", "+ `tracker.scale.depth_views=1 tracker.scale.temporal=false "
           "tracker.scale.camera_height_from_data=false`", expect={"tracker.scale.temporal": "false"}),
    RunRow("fps_kitti06_dense_refine", "same, dense flow refinement only (the faster choice)",
           "+ `flow.refine.mode=dense`", expect={"flow.refine.mode": "dense"}),
    RunRow("fps_kitti06_dis", "same, classical flow (OpenCV DIS, medium)", "+ `flow=dis`", expect={"flow": "dis"}),
    RunRow("fps_kitti06_paper_pipeline", "same, the paper's pipeline (raw network flow, per-frame one-view scale)",
           "+ `experiment=paper`", expect={"experiment": "paper"}),
    RunRow("fps_synthetic_network", "synthetic drive, 30 frames, shipped networks", "python infer.py",
           expect={"data": "synthetic"}),
    RunRow("fps_synthetic_oracle", "synthetic drive, 30 frames, true flow and depth",
           "python infer.py flow=oracle depth=oracle", expect={"flow": "oracle", "depth": "oracle"}),
    RunRow("fps_synthetic_oracle_geometry", "same, the geometry alone (no photometric road scale, whose 1–2 % per "
           "frame is the rest of the row above)", "+ `tracker.road_alignment.enabled=false`",
           [Target("RPE ≤ 1e-3 m", "rpe_m", "<=", 1e-3)],
           expect={"flow": "oracle", "depth": "oracle", "tracker.road_alignment.enabled": "false"}),
]


@dataclass
class Inputs:
    """Where the tables' JSON lives (command-line options)."""

    bench: list[Path]
    ablations: Path
    runs: dict[str, Path]
    ablation_dirs: dict[str, Path]
    machine: str
    partial: bool
    _cache: dict[str, list[Measured]] = field(default_factory=dict)

    def run_records(self, row: RunRow) -> list[Measured]:
        """The results of a headline row (read and checked once)."""
        if row.name in self._cache:
            return self._cache[row.name]
        if row.name in self.runs:
            found = [read_run(self.runs[row.name], self.machine)]
        else:
            found = []
            for folder in self.bench:
                for candidate in (folder / f"{row.name}.json", folder / row.name / "summary.json"):
                    if candidate.is_file():
                        found.append(read_run(candidate, self.machine))
                        break
        for record in found:
            row.check(record)
        self._cache[row.name] = found
        return found

    def bench_records(self, name: str) -> list[Measured]:
        return [read_json(f / f"{name}.json", self.machine) for f in self.bench if (f / f"{name}.json").is_file()]

    def where(self, name: str) -> str:
        return " or ".join(str(f / f"{name}.json") for f in self.bench) or f"{name}.json (no --bench folder)"


def _complete(rows: list[tuple[Any, list[Measured]]], inputs: Inputs) -> list[tuple[Any, list[Measured]]]:
    missing = list(dict.fromkeys(row.name for row, recs in rows if not recs))
    if missing and (not inputs.partial or len(missing) == len(rows)):
        raise MissingInput("no result for " + ", ".join(f"{m} ({inputs.where(m)})" for m in missing))
    return [(row, recs) for row, recs in rows if recs]


def _trackers(records: list[Measured]) -> str:
    fb = records[0].data.get("fallback") or {}
    counts = fb.get("trackers") or {}
    text = ", ".join(f"{k} {v}" for k, v in sorted(counts.items(), key=lambda kv: -kv[1]))
    cm = span([100 * (r.data.get("fallback") or {}).get("constant_motion_rate", 0.0) for r in records],
              lambda x: f"{x:.0f}")
    pnp = span([100 * (r.data.get("fallback") or {}).get("pnp_failed_rate", 0.0) for r in records],
               lambda x: f"{x:.0f}")
    return f"{text}; constant motion {cm} %, PnP failed {pnp} %"


def table_headline(inputs: Inputs) -> str:
    rows = _complete([(row, inputs.run_records(row)) for row in HEADLINE_ROWS], inputs)
    out = []
    for row, recs in rows:
        d = [r.data for r in recs]
        fps = span([x.get("fps") for x in d], fps_fmt)
        wo = [x.get("fps_without_loading") for x in d]
        load_share = [x["timing_ms_per_frame"].get("load", 0.0) * x["fps"] / 1000.0 for x in d if x.get("fps")]
        if load_share and max(load_share) > 0.1:  # the synthetic world is rendered on the fly: say what a camera costs
            fps += f" ({span(wo, fps_fmt)} without loading)"
        cmd = row.command if row.command.startswith("+") else f"`{row.command}`"
        out.append([row.label, cmd, f"{span([x.get('rpe_m') for x in d])} / {span([x.get('rpe_deg') for x in d])}",
                    span([x.get("ate_m") for x in d]), _trackers(recs), fps,
                    "; ".join(t.verdict(recs) for t in row.targets), measured_on(recs)])
    return markdown(["run", "command", "RPE m / deg", "ATE m", "trackers used", "FPS", "target", "measured"], out)


def table_timing(inputs: Inputs) -> str:
    rows = _complete([(row, inputs.run_records(row)) for row in HEADLINE_ROWS], inputs)
    stages: list[str] = []
    for _, recs in rows:
        for r in recs:
            stages += [s for s in r.data["timing_ms_per_frame"] if s not in stages]
    out = [[row.label] + [span([r.data["timing_ms_per_frame"].get(s) for r in recs], lambda x: f"{x:.0f}")
                          for s in stages] + [measured_on(recs)] for row, recs in rows]
    return markdown(["run (ms/frame)", *stages, "measured"], out)


@dataclass
class ComponentRow:
    name: str  # benchmarks/run_all.sh's JSON name
    label: str
    command: str
    target: str
    render: Callable[[dict[str, Any]], str]


def _flow_net(d: dict[str, Any]) -> str:
    fb = d["forward_backward_640x192"]
    return ", ".join(f"{v} {fb[v]['median_ms']:.0f} ms" + (" (shipped)" if v == "small" else "")
                     for v in ("default", "small", "tiny") if v in fb)


def _tracker(d: dict[str, Any]) -> str:
    ours, cv = d["dfvo"], d.get("opencv")
    text = f"{ours['ms_per_frame']:.0f} ms/frame at batch {d['setup']['batch']}"
    if cv:
        text += (f" (OpenCV findEssentialMat + recoverPose {cv['ms_per_frame']:.0f} ms, without GRIC or scale); rot "
                 f"err {ours['rot_err_deg']['mean']:.3f}° vs OpenCV {cv['rot_err_deg']['mean']:.3f}°, t-dir err "
                 f"{ours['trans_dir_err_deg']['mean']:.2f}° vs {cv['trans_dir_err_deg']['mean']:.2f}°")
    return text


def _odometry(d: dict[str, Any]) -> str:
    odo = d["odometry_synthetic_oracle"]
    batches = sorted((int(k.split("_")[1]), v) for k, v in odo.items() if k.startswith("batch_"))
    text = ", ".join(f"{v['ms_per_frame']:.0f} ms/frame at batch {b}" for b, v in batches)
    return f"{text}; max RPE {num(max(v['rpe_m_max'] for _, v in batches))} m"


def _render(d: dict[str, Any]) -> str:
    res = next((r for r in d["results"] if list(r.get("resolution", [])) == [192, 640]), d["results"][0])
    h, w = res["resolution"]
    return (f"{res['sequential']['median_ms'] / 1000:.2f} s median sequential, {res['cold']['median_ms'] / 1000:.2f} s "
            f"cold ({res['scenario']}, {w}×{h})")


COMPONENT_ROWS = [
    ComponentRow("depth_net", "depth network forward, 640×192 (scale-0 head, BN folded, channels_last)",
                 "python benchmarks/depth_net.py --threads 2 --skip-train", "≤ 150 ms",
                 lambda d: f"{d['depth_net_forward_ms']:.0f} ms (training forward {d['depth_net_train_forward_ms']:.0f}"
                           f" ms, encoder {d['encoder_forward_ms']:.0f} ms)"),
    ComponentRow("flow_net", "flow network forward + backward, 640×192 pair",
                 "python benchmarks/flow_net.py --skip-eval", "≤ 250 ms", _flow_net),
    ComponentRow("tracker", "tracker: 2000 correspondences, 5 RANSAC repeats, GRIC, simple scale",
                 "python benchmarks/tracker.py --threads 2", "≤ 50 ms", _tracker),
    ComponentRow("tracker", "odometry loop, synthetic world, true flow + depth", "python benchmarks/tracker.py "
                 "--threads 2", "", _odometry),
    ComponentRow("synthetic_render", "synthetic world, one frame with all outputs",
                 "python benchmarks/synthetic_render.py --frames 10 --threads 2", "≤ 0.2 s", _render),
    ComponentRow("eval_speed", "odometry evaluation, all 11 KITTI ground-truth sequences",
                 "python benchmarks/eval_speed.py", "",
                 lambda d: f"{d['wall_s']:.2f} s for {d['frames']} poses"),
]


def table_components(inputs: Inputs) -> str:
    rows = _complete([(row, inputs.bench_records(row.name)) for row in COMPONENT_ROWS], inputs)
    out = []
    for row, recs in rows:
        try:
            cells = sorted({row.render(r.data) for r in recs})
        except (KeyError, IndexError, TypeError) as err:
            raise MissingInput(f"{recs[0].path}: not the output of `{row.command}` (missing {err})") from None
        out.append([row.label, f"`{row.command}`", " / ".join(cells), row.target, measured_on(recs)])
    return markdown(["part", "command", "measured", "target", "measured on"], out)


ABLATIONS = {
    "ablation_kitti06": "scripts/run_ablation.sh runs/ablation_kitti06 data=kitti_odom data.root=ROOT seq=06",
    "ablation_synthetic_oracle": "scripts/run_ablation.sh runs/ablation_synthetic_oracle flow=oracle depth=oracle "
                                 "data.num_frames=100",
    "ablation_synthetic_network": "scripts/run_ablation.sh runs/ablation_synthetic_network data.num_frames=100",
}


def table_ablation(name: str, inputs: Inputs) -> str:
    folder = inputs.ablation_dirs.get(name, inputs.ablations / name)
    if not folder.is_dir() or not any(folder.rglob("summary.json")):
        raise MissingInput(f"no summary.json under {folder} (run `{ABLATIONS[name]}`)")
    runs = load_runs([folder])
    records = [Measured(Path(r["_path"]) / "summary.json", r, _date(r, Path(r["_path"]) / "summary.json"),
                        _machine(r, inputs.machine)) for r in runs]
    text = ablation_table(runs, fallback=True, reference=True).rstrip("\n")
    return f"{text}\n\nMeasured {measured_on(records)}; `{ABLATIONS[name]}`."


TABLES: dict[str, Callable[[Inputs], str]] = {
    "headline": table_headline,
    "timing": table_timing,
    "components": table_components,
    **{name: (lambda inputs, name=name: table_ablation(name, inputs)) for name in ABLATIONS},
}


# --------------------------------------------------------------------------------------------- the documents
def render_all(names: set[str], inputs: Inputs) -> tuple[dict[str, str], dict[str, str]]:
    """The tables that could be built (name → Markdown) and why the others could not (name → reason)."""
    built, kept = {}, {}
    for name in sorted(names):
        if name not in TABLES:
            kept[name] = f"unknown table (known: {', '.join(TABLES)})"
            continue
        try:
            built[name] = TABLES[name](inputs)
        except MissingInput as err:
            kept[name] = str(err)
    return built, kept


def update_file(path: Path, built: dict[str, str]) -> bool:
    """Replace the marked blocks of ``path`` whose table was built; True when the file changed."""
    text = path.read_text()
    new = MARKER.sub(lambda m: (f"<!-- results:{m['name']} -->\n{built[m['name']]}\n<!-- /results:{m['name']} -->"
                                if m["name"] in built else m.group(0)), text)
    if new != text:
        path.write_text(new)
    return new != text


def _pairs(values: list[str], option: str, parser: argparse.ArgumentParser) -> dict[str, Path]:
    out = {}
    for v in values:
        key, sep, path = v.partition("=")
        if not sep or not key or not path:
            parser.error(f"{option} {v!r}: expected NAME=PATH")
        out[key] = Path(path)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog="\n".join(__doc__.splitlines()[1:]))
    parser.add_argument("files", nargs="*", type=Path, default=list(DEFAULT_FILES),
                        help="Markdown files with <!-- results:NAME --> blocks (default: README.md docs/results.md)")
    parser.add_argument("--bench", action="append", type=Path, default=None,
                        help="folder of benchmark JSONs / run folders (repeatable; default: the checkout's runs/bench)")
    parser.add_argument("--ablations", type=Path, default=REPO / "runs",
                        help="folder holding the ablation_* sweep folders (default: the checkout's runs/)")
    parser.add_argument("--run", action="append", default=[], metavar="ROW=PATH",
                        help=f"a headline row from this run folder or JSON; rows: "
                             f"{', '.join(r.name for r in HEADLINE_ROWS)}")
    parser.add_argument("--ablation", action="append", default=[], metavar="NAME=PATH",
                        help=f"an ablation table from this sweep folder; names: {', '.join(ABLATIONS)}")
    parser.add_argument("--machine", default="machine not recorded",
                        help="machine description for results that do not record one (infer run folders)")
    parser.add_argument("--partial", action="store_true", help="render the rows that have data, drop the others")
    parser.add_argument("--print", dest="print_only", action="store_true",
                        help="print the tables that could be built; write no file")
    args = parser.parse_args(argv)
    inputs = Inputs(bench=args.bench or [REPO / "runs" / "bench"], ablations=args.ablations,
                    runs=_pairs(args.run, "--run", parser), ablation_dirs=_pairs(args.ablation, "--ablation", parser),
                    machine=args.machine, partial=args.partial)
    unknown = set(inputs.runs) - {r.name for r in HEADLINE_ROWS}
    if unknown:
        parser.error(f"--run {', '.join(sorted(unknown))}: expected one of {', '.join(r.name for r in HEADLINE_ROWS)}")
    names = set(TABLES)
    if not args.print_only:
        for path in args.files:
            if not path.is_file():
                parser.error(f"{path}: no such Markdown file")
        names = {m["name"] for path in args.files for m in MARKER.finditer(path.read_text())}
    built, kept = render_all(names, inputs)
    for name, reason in kept.items():
        print(f"results:{name}: kept as it is ({reason})", file=sys.stderr)
    if args.print_only:
        for name, text in built.items():
            print(f"<!-- results:{name} -->\n{text}\n<!-- /results:{name} -->\n")
        return 0
    for path in args.files:
        changed = update_file(path, built)
        print(f"{path}: {'updated' if changed else 'unchanged'}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
