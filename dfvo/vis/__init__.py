"""Pictures of tensors for any viewer: flow fields and scalar maps as colour images (:mod:`dfvo.vis.colour`), used
by the Rerun recording (:mod:`dfvo.viewer`), the TensorBoard images of inference and training, and the docs' figures.

At the bottom of the layers: plain tensor-to-image functions, no other dfvo import.
"""
