"""Speed benchmarks: each script measures time, memory or throughput and prints one JSON object; ``run_all.sh`` runs
the set behind the README's tables. They import only :mod:`dfvo`: run them as ``python benchmarks/NAME.py`` with dfvo
installed (``pip install -e .``), or as ``python -m benchmarks.NAME`` from the repository root of a checkout. Accuracy
studies live in ``studies/``."""
