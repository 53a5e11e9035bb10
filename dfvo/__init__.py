"""dfvo: monocular visual odometry from learned depth and optical flow plus multi-view geometry (DF-VO of Zhan et al.,
rebuilt in PyTorch + Kornia).

The commands are ``dfvo-infer``, ``dfvo-train`` and ``dfvo-eval`` (:mod:`dfvo.cli`); the subpackages and the layer
order their imports follow are mapped in ``docs/architecture.md``.
"""

__version__ = "0.1.0"
