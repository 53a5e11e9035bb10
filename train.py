"""Train a dfvo network: ``python train.py model=depth_stereo|depth_mono|depth_mono_sc|flow_* data=...``.

See ``conf/train.yaml``; the logic lives in :func:`dfvo.training.runner.run_training`.
"""

import hydra
from omegaconf import DictConfig

from dfvo.training.runner import run_training


@hydra.main(config_path="conf", config_name="train", version_base="1.3")
def main(cfg: DictConfig) -> None:
    result = run_training(cfg)
    print(f"done: step {result['global_step']}, last checkpoint {result['last_ckpt']}, best {result['best_ckpt']}")


if __name__ == "__main__":
    main()
