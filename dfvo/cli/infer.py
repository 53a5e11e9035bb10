"""``dfvo-infer`` / ``python infer.py``: run DF-VO on one sequence (logic in :mod:`dfvo.inference`).

    dfvo-infer                                                  # built-in synthetic sequence
    dfvo-infer data=kitti_odom data.root=ROOT seq=06 tracker=hybrid out_dir=OUT
    dfvo-infer -m tracker=hybrid,pnp correspondence=local_best_k,best_n,uniform   # parallel ablation
"""

from __future__ import annotations

import hydra
from omegaconf import DictConfig


@hydra.main(config_path="pkg://dfvo.conf.infer", config_name="infer", version_base="1.3")
def main(cfg: DictConfig) -> float | None:
    from dfvo.inference.pipeline import run_inference

    summary = run_inference(cfg)
    metrics = summary.get("metrics") or {}
    return metrics.get("rpe_m")


if __name__ == "__main__":
    main()
