"""CPU inference runtimes for the flow and depth networks: ONNX Runtime and OpenVINO, PyTorch the fallback.

``flow.runtime.kind`` / ``depth.runtime.kind`` (:class:`dfvo.sources.config.RuntimeConfig`; ``runtime=openvino``
sets both) choose what runs a network source's network. ``torch`` runs the PyTorch module as it is. ``onnxruntime``
and ``openvino`` run the same network exported to ONNX (:mod:`dfvo.sources.runtime.export`): the export is made from the
checkpoint the source loaded, on first use, into a cache folder (``runtime.cache_dir``), and it records the
checkpoint's sha256 and the export settings in the model's metadata; a cached model whose record does not match is
exported again (one log line), never used. Both runtimes come with the ``fast`` extra (``pip install "dfvo[fast]"``);
asking for one without it fails with one line naming the extra (:func:`dfvo.sources.runtime.engines.require_runtime`).

Convention: the exported graphs take and give the tensors of the PyTorch modules they replace, batch-first, at the
network's input size (``FlowNet.forward_backward``: images (B,3,h,w) in [0,1] → forward and backward flow (B,2,h,w)
in pixels; depth: images (B,3,h,w) → depth (B,1,h,w) in the network's units); the batch size is free.

Modules: :mod:`dfvo.sources.runtime.export` (the export and its cache), :mod:`dfvo.sources.runtime.engines` (the
runtimes); ``python -m dfvo.sources.runtime`` exports ahead of a run.
"""
