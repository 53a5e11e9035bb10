"""One inference run (``dfvo-infer`` / ``infer.py``): the configuration (:mod:`dfvo.inference.config`), the frames of
any dataset at the working size (:mod:`dfvo.inference.frames`), the loop frames -> sources -> tracker
(:mod:`dfvo.inference.loop`), the outputs written as frames arrive and the report at the end; built and run by
:func:`dfvo.inference.pipeline.run_inference`."""
