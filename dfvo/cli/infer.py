"""``dfvo-infer`` / ``python infer.py``: run DF-VO on one sequence (logic in :mod:`dfvo.inference`).

    dfvo-infer                                                  # built-in synthetic sequence
    dfvo-infer data=kitti_odom data.root=ROOT seq=06 tracker=hybrid out_dir=OUT
    dfvo-infer seq=10                                           # KITTI odometry 10 from $DFVO_KITTI_ODOM_ROOT
    dfvo-infer -m tracker=hybrid,pnp correspondence=local_best_k,best_n,uniform   # parallel ablation

Expected failures (bad data, settings, checkpoints) end with one line on stderr and the traceback in
``OUT/infer.log`` (``verbose=true`` raises them with their traceback). Ctrl-C or SIGTERM stop the run after its
partial outputs are written (exit status 128 + signal number).
"""

from __future__ import annotations

import hydra
from omegaconf import DictConfig

from dfvo.cli.errors import EXPECTED_ERRORS, report_error
from dfvo.inference.config import register_configs

register_configs()


@hydra.main(config_path="pkg://dfvo.conf.infer", config_name="infer", version_base="1.3")
def main(cfg: DictConfig) -> float | None:
    from dfvo.inference.pipeline import RunInterrupted, run_inference

    try:
        summary = run_inference(cfg)
    except RunInterrupted as err:
        report_error("dfvo-infer", f"interrupted by {err}; the poses so far, their metrics and plots are written",
                     exit_code=128 + err.signum)
    except EXPECTED_ERRORS as err:
        if cfg.get("verbose", False):
            raise
        report_error("dfvo-infer", str(err), exc=err)
    metrics = summary.get("metrics") or {}
    return metrics.get("rpe_m")


if __name__ == "__main__":
    main()
