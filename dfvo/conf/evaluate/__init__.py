"""Config tree of ``python -m dfvo.evaluate`` / ``dfvo-eval`` (``evaluate.yaml``).

Importing it registers the typed schema ``evaluate_schema`` (:class:`dfvo.cli.evaluate.EvaluateConfig`) that
``evaluate.yaml`` starts from, so that composing ``pkg://dfvo.conf.evaluate`` works from any entry point.
"""

from dfvo.cli.evaluate import register_schema

register_schema()
