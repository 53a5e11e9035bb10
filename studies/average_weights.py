"""The plain mean of several exported networks' weights (``weights_step{N}.safetensors`` of one run): parameters and
floating-point buffers averaged, integer buffers and the metadata taken from the last file. Writes one
``.safetensors`` in the files' dtype and prints its path.

    python studies/average_weights.py --out RUNS/depth_scene/avg_2000_4000.safetensors \\
        RUNS/depth_scene/weights_step2000.safetensors RUNS/depth_scene/weights_step3000.safetensors \\
        RUNS/depth_scene/weights_step4000.safetensors

(``trainer.ema_decay`` does the same inside a run, as an exponential moving average.)
"""

from __future__ import annotations

import argparse

from safetensors import safe_open
from safetensors.torch import load_file, save_file


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("weights", nargs="+")
    p.add_argument("--out", required=True)
    a = p.parse_args()
    states = [load_file(w) for w in a.weights]
    keys = set(states[0])
    for w, s in zip(a.weights, states, strict=True):
        if set(s) != keys:
            raise SystemExit(f"{w}: its tensors differ from {a.weights[0]}'s; expected files of one network")
    out = {}
    for k, last in states[-1].items():
        out[k] = (sum(s[k].float() for s in states) / len(states)).to(last.dtype) if last.is_floating_point() else last
    with safe_open(a.weights[-1], "pt") as f:
        meta = dict(f.metadata() or {})
    meta["source"] = "mean of " + ", ".join(a.weights)
    save_file(out, a.out, metadata=meta)
    print(a.out)


if __name__ == "__main__":
    main()
