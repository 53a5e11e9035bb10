#!/usr/bin/env bash
# The benchmarks behind the README's "Status and measured numbers" section, in one go (~3 min on the 2-core CPU,
# idle; the flow-quality numbers come from benchmarks/kitti_flow_quality.py, the ablations from scripts/run_ablation.sh).
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
run depth_net python benchmarks/depth_net.py --threads 2 --skip-train
run flow_net python benchmarks/flow_net.py --skip-eval
run tracker python benchmarks/tracker.py --threads 2
run eval_speed python benchmarks/eval_speed.py
run synthetic_render python benchmarks/synthetic_render.py --frames 10 --threads 2
run depth_scale python benchmarks/depth_scale_consistency.py
if python infer.py data=kitti_odom data.root="$KITTI" seq=06 out_dir="$OUT/kitti06" progress=false >"$OUT/kitti06.log" 2>&1
then
    run error_decomposition python benchmarks/error_decomposition.py --gt "$KITTI/poses/06.txt" --pred "$OUT/kitti06/06.txt"
else
    echo "infer.py on KITTI 06 failed: see $OUT/kitti06.log" >&2
fi
