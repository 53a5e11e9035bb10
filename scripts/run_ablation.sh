#!/usr/bin/env bash
# One-factor-at-a-time ablation in the layout of the paper's table: a reference run, then one sweep per factor, each
# into its own folder under OUT; then the markdown table (rows = how a run differs from the reference).
#
#   scripts/run_ablation.sh OUT [infer.py overrides shared by every run...]
#   scripts/run_ablation.sh runs/ablation_kitti06 data=kitti_odom data.root=../shared/data/kitti_odom seq=06
#   scripts/run_ablation.sh runs/ablation_synthetic flow=oracle depth=oracle data.num_frames=100
#
# The reference is infer.py's default configuration (hybrid tracker, local best-K, simple scale from both frames'
# depths, GRIC, 640x192, refined network flow); flow=dis (OpenCV DIS, the classical baseline) is a row of its own.
# Sweeps run in parallel through the configured Hydra launcher (joblib, 2 processes).
set -euo pipefail
if [[ $# -lt 1 ]]; then
    echo "usage: $0 OUT [infer.py overrides...]" >&2
    exit 2
fi
OUT="$1"
shift
cd "$(dirname "$0")/.."
mkdir -p "$OUT"
sweep() {  # sweep NAME OVERRIDES...
    local name="$1"
    shift
    python infer.py -m "$@" "out_dir=$OUT/$name" progress=false "${COMMON[@]}"
}
COMMON=("$@")
ORACLE=0
for arg in "$@"; do [[ "$arg" == flow=oracle ]] && ORACLE=1; done
sweep tracker tracker=hybrid,pnp,e          # hybrid = the reference run
sweep correspondence correspondence=uniform,best_n
sweep scale scale=iterative
sweep scale_views tracker.scale.depth_views=1   # the paper's one-view scale
# the scale over time and the camera-height prior (docs/scale.md), each off alone and both off (the paper's
# per-frame CNN-depth scale); the camera height is on where the dataset sets data.camera_height (KITTI)
sweep scale_temporal tracker.scale.temporal=false
sweep scale_height tracker.scale.camera_height_from_data=false
sweep scale_per_frame tracker.scale.temporal=false tracker.scale.camera_height_from_data=false
sweep gates tracker.gate.enabled=false
# issue 24's additions, each off (or on, for fuse_pnp) alone (docs/scale.md: the panel of every KITTI snippet)
sweep road_alignment tracker.road_alignment.enabled=false
sweep parallax_rule tracker.model_selection.min_parallax_px=null
sweep fuse_pnp tracker.scale.fuse_pnp=true
sweep filter_start tracker.scale_filter.warmup_frames=0
sweep height_estimate tracker.camera_height.estimate=false
sweep model_selection model_selection=flow
sweep img_res img_res=full
if [[ $ORACLE -eq 0 ]]; then                  # factors of the network flow
    sweep flow_refine flow.refine.iterations=0
    sweep flow_refine_mode flow.refine.mode=dense,pyramid   # the dense stage alone (faster), the pyramid alone
    sweep online online_finetune=true
    # the classical baseline (OpenCV DIS, medium preset): the row that says what the learned flow buys
    if python -c "import cv2" 2>/dev/null; then
        sweep flow_dis flow=dis
    else
        echo "$0: no flow=dis row: OpenCV is missing (pip install -e \".[classical]\")" >&2
    fi
fi
python scripts/aggregate_ablation.py "$OUT" --reference --fallback --out "$OUT/table.md"
