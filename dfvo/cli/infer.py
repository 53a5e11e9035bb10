"""``dfvo-infer`` / ``python infer.py``: run DF-VO on one sequence (logic in :mod:`dfvo.inference`).

    dfvo-infer                                                  # built-in synthetic sequence
    dfvo-infer data=kitti_odom data.root=ROOT seq=06 tracker=hybrid out_dir=OUT
    dfvo-infer seq=10                                           # KITTI odometry 10 from $DFVO_KITTI_ODOM_ROOT
    dfvo-infer -m tracker=hybrid,pnp correspondence=local_best_k,best_n,uniform   # parallel ablation

Expected failures (bad data, settings, checkpoints, a config Hydra cannot compose) end with one line on stderr and
the traceback in ``OUT/infer.log`` (``verbose=true`` shows the traceback instead; :mod:`dfvo.cli.errors`).
Ctrl-C or SIGTERM stop the run after its partial outputs are written (exit status 128 + signal number); a signal
before the first frame or after the last one also ends with one line and that status. Any other error mid-run also
leaves the partial outputs, marked partial. A finished run's last line names its output folder. One run at a time
per output folder (a lock); a rerun into a folder replaces the earlier run's outputs.
"""

from __future__ import annotations

import signal
import sys
from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig

from dfvo.cli.errors import EXPECTED_ERRORS, argv_value, guard_log_files, report_error, run_reporting_errors
from dfvo.inference.config import register_configs
from dfvo.inference.pipeline import run_inference
from dfvo.inference.recording import RunInterrupted

__all__ = ["main", "infer_app"]

TOOL = "dfvo-infer"
register_configs()


class _Stopped(KeyboardInterrupt):
    """SIGINT/SIGTERM outside the tracking loop (while loading, or while writing the results)."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


def _raise_stopped(signum: int, frame: Any) -> None:
    raise _Stopped(signum)


def _install_handlers() -> dict[int, Any]:
    """SIGINT and SIGTERM raise :class:`_Stopped` (the pipeline's own handlers take over during the loop)."""
    previous: dict[int, Any] = {}
    for sig in (signal.SIGINT, signal.SIGTERM):
        try:
            previous[sig] = signal.signal(sig, _raise_stopped)
        except ValueError:  # not the main thread (some launchers): keep the defaults
            pass
    return previous


@hydra.main(config_path="pkg://dfvo.conf.infer", config_name="infer", version_base="1.3")
def infer_app(cfg: DictConfig) -> float | None:
    """The Hydra task: one run of :func:`dfvo.inference.pipeline.run_inference` (one job of a multirun)."""
    previous = _install_handlers()
    guard_log_files()  # a full disk: one error line, not logging's traceback per record
    try:
        summary = run_inference(cfg)
    except RunInterrupted as err:
        report_error(TOOL, f"interrupted by {err}; the poses so far, their metrics and plots are written",
                     exit_code=128 + err.signum)
    except KeyboardInterrupt as err:  # a signal while loading or while writing the results
        signum = getattr(err, "signum", signal.SIGINT)
        report_error(TOOL, f"interrupted by {signal.Signals(signum).name} before the run finished (while loading "
                     f"or writing results); its outputs are missing or incomplete", exit_code=128 + signum)
    except EXPECTED_ERRORS as err:
        if cfg.get("verbose", False):
            raise
        written = getattr(err, "dfvo_partial", None)  # stopped mid-run: the partial outputs were written
        done = "" if written is None else (f"; the first {written[0]} of {written[1]} poses, their metrics and plots "
                                           "are written, marked partial")
        report_error(TOOL, f"{err}{done}", exc=err)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    print(f"{TOOL}: outputs in {Path(summary['pose_file']).parent}", flush=True)  # the last line: where they went
    metrics = summary.get("metrics") or {}
    return metrics.get("rpe_m")


def _lock_out_dir(argv: list[str]) -> Any:
    """The lock of ``out_dir=`` of the command line, taken before Hydra writes its files into the folder (None when
    out_dir is not given literally or cannot be made: the run then reports that itself; and under ``-m``, whose jobs
    lock their own subfolders). A folder in use by another live run ends the command with one line."""
    from dfvo.inference.outputs import OutDirBusy, lock_out_dir, prepare_out_dir

    out_dir = argv_value(argv, "out_dir")
    if not out_dir or "${" in out_dir or "-m" in argv or "--multirun" in argv:
        return None
    try:
        return lock_out_dir(prepare_out_dir(out_dir))
    except OutDirBusy as err:
        print(f"{TOOL}: error: {err}", file=sys.stderr, flush=True)
        sys.exit(1)
    except (OSError, ValueError):
        return None


def main() -> None:
    """Entry point of ``dfvo-infer`` and ``python infer.py``: :func:`infer_app` with one-line config errors, holding
    the lock of ``out_dir`` (one run per folder) from before Hydra writes into it."""
    lock = _lock_out_dir(sys.argv[1:])
    try:
        run_reporting_errors(TOOL, infer_app, "infer.log")
    finally:
        if lock is not None:
            lock.release()


if __name__ == "__main__":
    main()
