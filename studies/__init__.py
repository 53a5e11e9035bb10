"""Accuracy studies behind the figures of the README and ``docs/`` (learned vs classical flow, scale, depth
consistency, flow quality on KITTI, error decomposition, depth checkpoints); each prints one JSON object. They import
only :mod:`dfvo`: run them as ``python studies/NAME.py`` with dfvo installed (``pip install -e .``), or as
``python -m studies.NAME`` from the repository root of a checkout. Speed is measured by ``benchmarks/``."""
