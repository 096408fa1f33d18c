#!/usr/bin/env bash
# Set up (idempotent) and run the main job on the embedded default dataset.
# Today: synthesise the default dataset (once), then two OS processes talk over the project's
# own interfaces: generation_node serves generate_hypothesis, a client replays a frame's ground
# truth on perception/ground_truth and asks for hypotheses over a noise sweep.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
source "$ROOT/scripts/setup_env.sh"
cd "$ROOT"
DATA="${PERCEPTION_CONFIG_DATA:-$ROOT/data/default}"

if [ ! -f "$DATA/models/models_info.json" ]; then  # written last: the generator renames a finished dataset into place
  say "synthesising the default dataset into $DATA"
  perception-config synth --out "$DATA" --scenes 4 --images-per-scene 10 --seed 0
fi
say "dataset: $DATA"
perception-config show --dataset "$DATA" --out "$ROOT/outputs/demo/frame.png"

say "starting generation_node (its own process, loopback only, ROS_DOMAIN_ID=${ROS_DOMAIN_ID:-42})"
mkdir -p "$ROOT/outputs/demo"
generation_node --ros-args -p models_dir:="$DATA/models" > "$ROOT/outputs/demo/generation_node.log" 2>&1 &
NODE_PID=$!
trap 'kill -INT $NODE_PID 2>/dev/null; wait $NODE_PID 2>/dev/null || true' EXIT
"$PY" -m perception_config.ros.generation_demo --dataset "$DATA"
say "node log: outputs/demo/generation_node.log; frame picture: outputs/demo/frame.png"
