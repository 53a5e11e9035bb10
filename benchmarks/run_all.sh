#!/usr/bin/env bash
# The speed benchmarks behind the README's "Status and measured numbers" section, in one go (~3 min on the 2-core CPU,
# idle); the accuracy studies are studies/run_all.sh (and studies/kitti_flow_quality.py, studies/flow_vs_classical.py),
# the ablations scripts/run_ablation.sh.
# Each benchmark's JSON goes to OUT/NAME.json (stderr to OUT/NAME.err); the KITTI runs need ../shared/data.
#
#   benchmarks/run_all.sh [OUT]        # default OUT: runs/bench
set -uo pipefail
cd "$(dirname "$0")/.."
OUT="${1:-runs/bench}"
KITTI=../shared/data/kitti_odom
mkdir -p "$OUT"
run() {  # run NAME COMMAND...
    local name="$1"
    shift
    echo "== $name (load $(cut -d' ' -f1 /proc/loadavg))"
    "$@" >"$OUT/$name.json" 2>"$OUT/$name.err"
    echo "rc=$?"
}
run fps_kitti06 python benchmarks/infer_fps.py --data kitti_odom --root "$KITTI" --seq 06 --frames 51 --sources network
run fps_kitti06_per_frame_scale python benchmarks/infer_fps.py --data kitti_odom --root "$KITTI" --seq 06 --frames 51 \
    --sources network --overrides tracker.scale.depth_views=1 tracker.scale.temporal=false \
    tracker.scale.camera_height_from_data=false
run fps_kitti06_dense_refine python benchmarks/infer_fps.py --data kitti_odom --root "$KITTI" --seq 06 --frames 51 \
    --sources network --overrides flow.refine.mode=dense
run fps_kitti06_dis python benchmarks/infer_fps.py --data kitti_odom --root "$KITTI" --seq 06 --frames 51 \
    --sources dis
run fps_kitti06_paper_pipeline python benchmarks/infer_fps.py --data kitti_odom --root "$KITTI" --seq 06 --frames 51 \
    --sources network --overrides experiment=paper
run fps_synthetic_network python benchmarks/infer_fps.py --data synthetic --frames 30 --sources network
run fps_synthetic_oracle python benchmarks/infer_fps.py --data synthetic --frames 30 --sources oracle
run fps_synthetic_oracle_geometry python benchmarks/infer_fps.py --data synthetic --frames 30 --sources oracle \
    --overrides tracker.road_alignment.enabled=false
run depth_net python benchmarks/depth_net.py --threads 2 --skip-train
run flow_net python benchmarks/flow_net.py --skip-eval
run tracker python benchmarks/tracker.py --threads 2
run eval_speed python benchmarks/eval_speed.py
run synthetic_render python benchmarks/synthetic_render.py --frames 10 --threads 2
