"""``dfvo-train`` / ``python train.py``: train a dfvo network (logic in :mod:`dfvo.training.runner`).

    dfvo-train model=depth_stereo|depth_mono|depth_mono_sc|flow_supervised|flow_self data=KIND [trainer=PRESET]
    dfvo-train trainer=smoke                          # 3 steps + one validation batch: checks a setup end to end
    dfvo-train trainer=gpu data.batch_size=16         # one GPU, bf16-mixed, channels_last
    dfvo-train --cfg job                              # the composed config, every default included

The settings and their defaults: :mod:`dfvo.training.config`. Expected failures (bad data, settings, checkpoints, a
non-finite loss) end with one line on stderr and the traceback in the run's Hydra log (``verbose=true`` raises them
with their traceback). SIGTERM / SIGINT stop after the step in progress with ``last.ckpt`` written, one line, and
exit status 143 / 130 (:mod:`dfvo.training.stop_signals`).
"""

from __future__ import annotations

import hydra
from omegaconf import DictConfig

from dfvo.cli.errors import EXPECTED_ERRORS, report_error, run_reporting_errors
from dfvo.training.config import register_configs

register_configs()


@hydra.main(config_path="pkg://dfvo.conf.train", config_name="train", version_base="1.3")
def train_app(cfg: DictConfig) -> None:
    """The Hydra task: one training run (:func:`dfvo.training.runner.run_training`)."""
    from dfvo.training.runner import (  # deferred: Lightning is slow to import; --help is not
        TrainingInterrupted,
        run_training,
    )

    try:
        result = run_training(cfg)
    except TrainingInterrupted as err:  # SIGTERM / SIGINT: last.ckpt written, exit 128 + signal (143 / 130)
        report_error("dfvo-train", str(err), exc=err, exit_code=err.exit_code)
    except (*EXPECTED_ERRORS, FloatingPointError) as err:
        if cfg.get("verbose", False):
            raise
        report_error("dfvo-train", str(err), exc=err)
    weights = f", weights {result['weights']}" if result["weights"] else ""
    best = f", best {result['best_ckpt']}" if result["best_ckpt"] != result["last_ckpt"] else ""
    print(f"done: step {result['global_step']}, last checkpoint {result['last_ckpt']}{best}{weights}")


def main() -> None:
    """Entry point of ``dfvo-train`` and ``python train.py``: :func:`train_app`, with a config Hydra cannot compose
    (an unknown key: the closest valid one) ending in one line."""
    run_reporting_errors("dfvo-train", train_app, None)


if __name__ == "__main__":
    main()
