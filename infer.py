"""DF-VO inference entry point (logic in :mod:`dfvo.inference.pipeline`).

    python infer.py                                                   # built-in synthetic sequence, oracle sources
    python infer.py data=kitti_odom data.root=ROOT seq=06 tracker=hybrid out_dir=OUT
    python infer.py -m tracker=hybrid,pnp correspondence=local_best_k,best_n,uniform   # parallel ablation

Inference datasets are the config group ``dataset`` mounted at ``data`` (``conf/dataset/*.yaml``; ``conf/data/`` is
the training datasets' group), so a command-line ``data=NAME`` is rewritten to ``dataset@data=NAME`` here.
"""

from __future__ import annotations

import sys

import hydra
from omegaconf import DictConfig


def _rewrite_data_override(argv: list[str]) -> list[str]:
    """``data=X`` selects the inference dataset group ``dataset@data``."""
    return ["dataset@data=" + a[len("data="):] if a.startswith("data=") else a for a in argv]


@hydra.main(config_path="conf", config_name="infer", version_base="1.3")
def main(cfg: DictConfig) -> float | None:
    from dfvo.inference.pipeline import run_inference

    summary = run_inference(cfg)
    metrics = summary.get("metrics") or {}
    return metrics.get("rpe_m")


if __name__ == "__main__":
    sys.argv[1:] = _rewrite_data_override(sys.argv[1:])
    main()
