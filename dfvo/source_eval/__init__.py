"""``dfvo-eval task=flow|depth``: a flow or depth source (a trained network, OpenCV DIS, or prediction files) run
over a benchmark's frames and scored against its ground truth: KITTI flow 2012/2015 (:mod:`dfvo.source_eval.flow`)
and the KITTI Eigen depth split (:mod:`dfvo.source_eval.depth`).

These drivers sit above :mod:`dfvo.sources` (they build sources) and :mod:`dfvo.data` (they read the benchmarks), so
that :mod:`dfvo.eval`, whose metric and report modules they use, stays at the bottom of the layers.
"""
