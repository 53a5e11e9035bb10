"""Dataset readers: KITTI odometry, KITTI raw, EuRoC, TUM RGB-D, image folders, videos, flow datasets (the synthetic
world that gives samples with the same keys is :mod:`dfvo.synthetic`).

Sample convention (every dataset returns a dict; the default collate stacks them batch-first):

==================  =============  =====================================================================
key                 shape          meaning
==================  =============  =====================================================================
``image``           (3,H,W)        frame i (the target / current frame), float in [0,1], RGB
``image_prev``      (3,H,W)        frame i-1 (temporal snippets only)
``image_next``      (3,H,W)        frame i+1 (temporal snippets only)
``image_right``     (3,H,W)        stereo partner of frame i (stereo samples only)
``K``               (3,3)          intrinsics of ``image`` at the working resolution, pixels
``T_right_left``    (4,4)          maps points of the left camera into the right camera (baseline b:
                                   translation (-b, 0, 0) for KITTI's rectified pairs)
``pose``            (4,4)          ``T_w_c`` of frame i when ground truth exists (absent otherwise)
``pose_prev/next``  (4,4)          ``T_w_c`` of frames i-1 / i+1 when known
``depth``           (1,H,W)        true depth of frame i in metres (synthetic world)
``flow_fwd``        (2,H,W)        true flow i→i+1 on image i's pixels (synthetic world)
``flow_bwd``        (2,H,W)        true flow i+1→i on image i+1's pixels (synthetic world)
``flow_fwd_valid``  (1,H,W) bool   pixel of i visible in i+1 (not occluded, lands inside the image)
``flow_bwd_valid``  (1,H,W) bool   same for the backward flow
``dynamic_mask``    (1,H,W) bool   pixel belongs to a moving object (synthetic world)
``index``           ()             integer frame index i in its sequence
==================  =============  =====================================================================

Images are always 3-channel (grayscale KITTI image_0 is replicated). Poses follow ``dfvo.geometry.se3``.
"""
