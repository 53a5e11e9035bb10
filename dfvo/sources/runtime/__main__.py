"""``python -m dfvo.sources.runtime flow|depth [--checkpoint F] [--input-size H W] [--cache-dir D]``: export a shipped
(or given) checkpoint's network to ONNX into the runtime cache ahead of a run (a run does it itself on first use),
and print the exported file's path."""

from __future__ import annotations

import argparse
import logging
import sys

from dfvo.io.checkpoint import CheckpointError, find_checkpoint
from dfvo.sources.networks import NetworkDepth, NetworkFlow
from dfvo.sources.runtime.engines import require_runtime
from dfvo.sources.runtime.export import exported_model


def main(argv: list[str] | None = None) -> None:
    """``python -m dfvo.sources.runtime flow|depth ...``: export a shipped (or given) checkpoint into the cache."""

    p = argparse.ArgumentParser(prog="python -m dfvo.sources.runtime", description=__doc__.splitlines()[0])
    p.add_argument("network", choices=["flow", "depth"])
    p.add_argument("--checkpoint", default=None, help="weights file (default: the shipped one)")
    p.add_argument("--input-size", type=int, nargs=2, default=None, metavar=("H", "W"),
                   help="network input size (default: the checkpoint's metadata)")
    p.add_argument("--cache-dir", default=None, help="export folder (default: $DFVO_CACHE_DIR/runtime or "
                   "~/.cache/dfvo/runtime)")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        require_runtime("onnxruntime", "python -m dfvo.sources.runtime", need_runtime=False)
        ckpt = find_checkpoint(args.checkpoint or f"checkpoints/{args.network}.safetensors", "--checkpoint")
        source = (NetworkFlow(ckpt, input_size=args.input_size) if args.network == "flow"
                  else NetworkDepth(ckpt, input_size=args.input_size))
        if source.input_size is None:
            raise ValueError(f"{ckpt}: no height/width in its metadata; give --input-size H W")
        size = source.input_size if args.network == "flow" else source.network_size(*source.input_size)
        spec = source.export_spec(size)
        path = exported_model(spec, lambda: source.model, args.cache_dir, "--cache-dir")
    except (CheckpointError, ValueError, OSError, ImportError) as err:
        print(f"python -m dfvo.sources.runtime: error: {err}", file=sys.stderr)
        sys.exit(1)
    print(path)


if __name__ == "__main__":
    main()
