"""File formats shared across the package, at the bottom of the layers (no other dfvo import): JSON results
(:mod:`dfvo.io.json_io`), network checkpoints (:mod:`dfvo.io.checkpoint`), trajectory files (:mod:`dfvo.io.trajectory`)
and the pairing of timed poses (:mod:`dfvo.io.association`), which the dataset readers and the evaluation share.
Image and flow files are the datasets' own (:mod:`dfvo.data.image_io`, :mod:`dfvo.data.flow_io`)."""
