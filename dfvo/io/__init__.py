"""File formats shared across the package: JSON results (:mod:`dfvo.io.json_io`) and network checkpoints
(:mod:`dfvo.io.checkpoint`). Trajectory files live in :mod:`dfvo.eval.trajectory_io`, flow files in
:mod:`dfvo.data.flow_io`."""
