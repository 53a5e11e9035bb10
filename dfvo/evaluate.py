"""``python -m dfvo.evaluate gt_dir=GT pred_dir=PRED align=7dof [seqs=[09,10]] [exclude=[01]] [out=metrics.json]
[plot_dir=DIR]``: KITTI odometry evaluation of folders of KITTI pose files; prints a table, writes JSON.

Arguments are Hydra-style ``key=value`` pairs parsed here so that sequence names keep their leading zeros.
"""

from __future__ import annotations

import sys
import warnings

from dfvo.eval.report import evaluate_sequences, format_table, write_json

KEYS = {"gt_dir", "pred_dir", "align", "seqs", "exclude", "out", "plot_dir"}


def _parse_list(key: str, value: str) -> list[str]:
    v = value.strip()
    if v.startswith("[") != v.endswith("]"):
        raise ValueError(f"{key}={value}: expected a list such as {key}=[09,10]")
    items = [s.strip().strip("'\"") for s in v.strip("[]").split(",")]
    return [s for s in items if s]


def parse_args(argv: list[str]) -> dict:
    """Parse ``key=value`` overrides into a dict (lists for ``seqs``/``exclude``, strings otherwise)."""
    args: dict = {"align": "7dof", "seqs": None, "exclude": None, "out": None, "plot_dir": None}
    for token in argv:
        key, sep, value = token.partition("=")
        key = key.lstrip("+")
        if not sep or key not in KEYS:
            raise ValueError(f"argument {token!r}: expected key=value with key in {sorted(KEYS)}")
        args[key] = _parse_list(key, value) if key in ("seqs", "exclude") else value
    for key in ("gt_dir", "pred_dir"):
        if key not in args:
            raise ValueError(f"missing required argument {key}=PATH")
    return args


def main(argv: list[str] | None = None) -> dict:
    """Run the command on ``argv`` (default ``sys.argv[1:]``); returns the ``evaluate_sequences`` result."""
    args = parse_args(sys.argv[1:] if argv is None else argv)
    with warnings.catch_warnings():  # the scale warning is printed once, under the table
        warnings.simplefilter("ignore", UserWarning)
        result = evaluate_sequences(args["gt_dir"], args["pred_dir"], seqs=args["seqs"], align=args["align"],
                                    exclude=args["exclude"], plot_dir=args["plot_dir"])
    print(format_table(result))
    if args["out"]:
        print(f"wrote {write_json(args['out'], result)}")
    return result


if __name__ == "__main__":
    try:
        main()
    except (ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)
