"""``python -m dfvo.evaluate gt_dir=GT pred_dir=PRED align=7dof [seqs=[09,10]] [exclude=[01]] [out=metrics.json]
[plot_dir=DIR]``: KITTI odometry evaluation of folders of KITTI pose files; prints a table, writes JSON.

Arguments are Hydra-style ``key=value`` pairs parsed here so that sequence names keep their leading zeros; integer
KITTI sequence ids are written with two digits (``seqs=[6]`` is ``06``), as ``infer.py seq=6`` names its ``06.txt``.
``-h`` / ``--help`` prints the usage.
"""

from __future__ import annotations

import sys
import warnings

from dfvo.eval.report import evaluate_sequences, format_table
from dfvo.io.json_io import write_json

KEYS = {"gt_dir", "pred_dir", "align", "seqs", "exclude", "out", "plot_dir"}
DEFAULTS: dict = {"align": "7dof", "seqs": None, "exclude": None, "out": None, "plot_dir": None}
USAGE = """usage: python -m dfvo.evaluate gt_dir=GT pred_dir=PRED [align=7dof] [seqs=[09,10]] [exclude=[01]]
                            [out=metrics.json] [plot_dir=DIR]

KITTI odometry evaluation of folders of KITTI pose files (<seq>.txt, 12 numbers a line): prints a table
(t_err %, r_err deg/100m, ATE, RPE per sequence and their average) and optionally writes JSON and plots.

keys (key=value):
  gt_dir=PATH     folder of ground-truth pose files (required)
  pred_dir=PATH   folder of predicted pose files, e.g. infer.py's out_dir (required)
  align=MODE      6dof | 7dof | scale | none (default: 7dof; monocular up-to-scale runs need 7dof or scale)
  seqs=[A,B]      sequences to evaluate (default: every <seq>.txt of pred_dir that has ground truth);
                  integer ids get two digits: seqs=[6] is 06
  exclude=[A]     sequences left out of the average (default: none; the DF-VO paper excludes 01)
  out=FILE        also write the metrics as JSON (default: none)
  plot_dir=DIR    also write <seq>_trajectory.png and <seq>_segment_errors.png (default: none)

example:
  python -m dfvo.evaluate gt_dir=../shared/data/kitti_odom/poses pred_dir=outputs/infer/run align=6dof seqs=[06]
"""


def sequence_name(seq: object) -> str:
    """KITTI sequence name of ``seq``: integer ids get two digits (``6`` -> ``"06"``), other names are kept.

    The rule :class:`dfvo.data.kitti_odometry.KittiOdometry` applies to ``infer.py seq=...`` (its pose file is
    ``<name>.txt``)."""
    text = str(seq)
    return text.zfill(2) if text.isdigit() else text


def _parse_list(key: str, value: str) -> list[str]:
    v = value.strip()
    if v.startswith("[") != v.endswith("]"):
        raise ValueError(f"{key}={value}: expected a list such as {key}=[09,10]")
    items = [s.strip().strip("'\"") for s in v.strip("[]").split(",")]
    return [s for s in items if s]


def parse_args(argv: list[str]) -> dict:
    """Parse ``key=value`` overrides into a dict (lists for ``seqs``/``exclude``, strings otherwise)."""
    args: dict = dict(DEFAULTS)
    for token in argv:
        key, sep, value = token.partition("=")
        key = key.lstrip("+")
        if not sep or key not in KEYS:
            raise ValueError(f"argument {token!r}: expected key=value with key in {sorted(KEYS)} "
                             "(python -m dfvo.evaluate --help)")
        if key in ("seqs", "exclude"):
            args[key] = [sequence_name(s) for s in _parse_list(key, value)]
        else:
            args[key] = value
    for key in ("gt_dir", "pred_dir"):
        if key not in args:
            raise ValueError(f"missing required argument {key}=PATH")
    return args


def main(argv: list[str] | None = None) -> dict:
    """Run the command on ``argv`` (default ``sys.argv[1:]``); returns the ``evaluate_sequences`` result
    (an empty dict after printing the usage for ``-h`` / ``--help``)."""
    argv = sys.argv[1:] if argv is None else argv
    if any(a in ("-h", "--help") for a in argv):
        print(USAGE, end="")
        return {}
    args = parse_args(argv)
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
