"""``dfvo-train`` / ``python train.py``: train a dfvo network (logic in :mod:`dfvo.training.runner`).

    dfvo-train model=depth_stereo|depth_mono|depth_mono_sc|flow_supervised|flow_self data=...
"""

from __future__ import annotations

import hydra
from omegaconf import DictConfig


@hydra.main(config_path="pkg://dfvo.conf.train", config_name="train", version_base="1.3")
def main(cfg: DictConfig) -> None:
    from dfvo.training.runner import run_training

    result = run_training(cfg)
    print(f"done: step {result['global_step']}, last checkpoint {result['last_ckpt']}, best {result['best_ckpt']}")


if __name__ == "__main__":
    main()
