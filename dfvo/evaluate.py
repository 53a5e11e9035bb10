"""``python -m dfvo.evaluate``: the same command as the installed ``dfvo-eval`` (:mod:`dfvo.cli.evaluate`)."""

from dfvo.cli.evaluate import main, parse_args  # noqa: F401  (parse_args: the composed options, for scripts)
from dfvo.eval.report import sequence_name  # noqa: F401

if __name__ == "__main__":
    main()
