"""Command-line entry points: ``dfvo-infer``, ``dfvo-train``, ``dfvo-eval`` (and ``infer.py``/``train.py``)."""
