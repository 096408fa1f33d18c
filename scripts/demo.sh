#!/usr/bin/env bash
# Set up (idempotent) and run the main job on the embedded default dataset:
#   1. synthesise the default dataset (once) and draw one frame with its ground truth;
#   2. fit the learned pick-success score on the train images (the test images stay unseen);
#   3. train the policy-gradient agent on the pipeline with that score (the recipe: a cost model
#      calibrated on this machine, so the reward does not depend on its load; a warm start that
#      imitates the best threshold rule searched on 48 train episodes; then 800 episodes at a
#      gentle learning rate; validation-based selection);
#   4. evaluate it against the oracle, best_static (the best fixed sequence found by search on the
#      train images), the engineer pipelines and the random agent over lambda = 0.1 .. 1.0 on the
#      test images (Fig. 5), print the table and one line: the agent against best_static and the
#      oracle, with 95 % intervals;
#   5. the robot cell without ground truth: train the agent on the cell pipeline (resting_pose,
#      ranked candidates, ppf, global_registration, ICP; only the simulated pick looks at the ground truth)
#      and evaluate it against best_static, the fixed ground-truth-free pipelines and the oracle;
#   6. through ROS 2: record test images to MCAP, replay them with bag_replay_node through the
#      operator nodes and the configurator running the trained policy (each its own process, then
#      all composed in one), estimate every object with estimate_pose and compare with the same
#      episodes in-process.
# Environment: DEMO_SCORE_EPISODES (episodes the score is fitted on, default 400), DEMO_EPISODES
# (training episodes, default 800), DEMO_EVAL_EPISODES (episodes per lambda, default 40),
# DEMO_LAMBDAS (default 0.1,0.3,0.5,0.7,1.0), DEMO_SEARCH_EPISODES (train episodes per lambda the
# best_static search plays, default 16), DEMO_SEED (training seed, default 0),
# DEMO_CELL_EPISODES (training episodes of the cell agent, default 400), DEMO_CELL_SEEDS (cell
# agents trained, the validation-best shipped, default 2), DEMO_CELL_EVAL_EPISODES (its evaluation
# episodes, default 40), DEMO_REPLAY_IMAGES (images replayed through ROS, default 8),
# PERCEPTION_CONFIG_DATA (dataset folder, default data/default), DEMO_WORKERS (Ray workers for
# training and evaluation, default 2 on a machine with 2+ cores; 1 = in-process, without Ray).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
source "$ROOT/scripts/setup_env.sh"
cd "$ROOT"
DATA="${PERCEPTION_CONFIG_DATA:-$ROOT/data/default}"
OUT="$ROOT/outputs/demo"
RUN="$ROOT/runs/demo-pg"
SCORE="$ROOT/runs/demo-score"
CELL_RUN="$ROOT/runs/demo-cell-pg"
mkdir -p "$OUT"
start=$(date +%s)
WORKERS="${DEMO_WORKERS:-$(( $(nproc) >= 2 ? 2 : 1 ))}"

if [ ! -f "$DATA/models/models_info.json" ]; then  # the generator renames a finished dataset into place
  say "1/6 synthesising the default dataset into $DATA"
  perception-config synth --out "$DATA" --scenes 4 --images-per-scene 10 --seed 0
else
  say "1/6 default dataset present: $DATA"
fi
perception-config show --dataset "$DATA" --out "$OUT/frame.png"

t_fit=$(date +%s)
say "2/6 fitting the pick-success score on the train images (${DEMO_SCORE_EPISODES:-400} episodes)"
perception-config fit-score --dataset "$DATA" --episodes "${DEMO_SCORE_EPISODES:-400}" --out "$SCORE" --quiet
# the shipped pick_success pipeline, with this score
sed "s#params: {model: pick_success}#params: {model: $SCORE}#" \
  "$("$PY" -c 'import perception_config.config as c, os; print(os.path.dirname(c.__file__))')/pick_success_pipeline.yaml" \
  > "$OUT/pick_success_pipeline.yaml"

t_train=$(date +%s)
say "3/6 training the policy-gradient agent (a warm start, then ${DEMO_EPISODES:-800} episodes, cost-model time)"
perception-config train --dataset "$DATA" --agent pg --pipeline "$OUT/pick_success_pipeline.yaml" --out "$RUN" \
  --episodes "${DEMO_EPISODES:-800}" --seed "${DEMO_SEED:-0}" --overwrite --workers "$WORKERS"

t_eval=$(date +%s)
say "4/6 evaluating over lambda = ${DEMO_LAMBDAS:-0.1,0.3,0.5,0.7,1.0} on the test images"
perception-config evaluate --dataset "$DATA" --policy "$RUN/policy.safetensors" --out "$OUT/evaluation" \
  --lambdas "${DEMO_LAMBDAS:-0.1,0.3,0.5,0.7,1.0}" --episodes "${DEMO_EVAL_EPISODES:-40}" --workers "$WORKERS" \
  --best-static-episodes "${DEMO_SEARCH_EPISODES:-16}"

t_cell=$(date +%s)
say "5/6 the cell without ground truth: pg on the cell pipeline (${DEMO_CELL_SEEDS:-2} seeds x ${DEMO_CELL_EPISODES:-400} episodes; the seed of lowest validation cost ships)"
perception-config train --dataset "$DATA" --agent pg --pipeline cell --out "$CELL_RUN" \
  --episodes "${DEMO_CELL_EPISODES:-400}" --seed "${DEMO_SEED:-0}" --seeds "${DEMO_CELL_SEEDS:-2}" --overwrite \
  --workers "$WORKERS"
# The cell's generator (resting_pose) has no noise level: one lambda, whose value is not used.
perception-config evaluate --dataset "$DATA" --policy "$CELL_RUN/policy.safetensors" --out "$OUT/cell" \
  --lambdas 0.5 --episodes "${DEMO_CELL_EVAL_EPISODES:-40}" --oracle-budget 300 --workers "$WORKERS" \
  --best-static-episodes "${DEMO_SEARCH_EPISODES:-16}"

t_ros=$(date +%s)
say "6/6 ROS 2: replaying ${DEMO_REPLAY_IMAGES:-8} test images through the nodes (loopback, ROS_DOMAIN_ID=${ROS_DOMAIN_ID:-42}), as separate processes, then composed in one"
perception-config replay-check --dataset "$DATA" --policy "$RUN/policy.safetensors" --out "$OUT/replay" \
  --images "${DEMO_REPLAY_IMAGES:-8}"
perception-config replay-check --dataset "$DATA" --policy "$RUN/policy.safetensors" --out "$OUT/replay_composed" \
  --images "${DEMO_REPLAY_IMAGES:-8}" --composed

t_end=$(date +%s)
table() { "$PY" -c 'import json, sys; from perception_config.learning.evaluation_export import format_table
print(format_table(json.load(open(sys.argv[1]))))' "$1"; }
say "the lambda study (simulated initialisation, the pipeline with the learned pick-success score):"
table "$OUT/evaluation/results.json"
perception-config study --verdict "$OUT/evaluation"
say "the cell without ground truth (cell pipeline: resting_pose + ranked candidates, ppf, global_registration, ICP):"
table "$OUT/cell/results.json"
perception-config study --verdict "$OUT/cell"
say "done in $(( $(date +%s) - start )) s: score fit $(( t_train - t_fit )) s, training $(( t_eval - t_train )) s, evaluation $(( t_cell - t_eval )) s, cell $(( t_ros - t_cell )) s, ROS $(( t_end - t_ros )) s (load $(cut -d" " -f1 /proc/loadavg)). Look at:"
echo "  $OUT/frame.png                      a frame with the ground truth overlaid"
echo "  $RUN/learning_curve.png      the training curve"
echo "  $OUT/evaluation/fig5.png           operations, time and first picks vs lambda (paper Fig. 5)"
echo "  $OUT/evaluation/lambda_grid.png    initial hypotheses per lambda (Fig. 4)"
echo "  $OUT/evaluation/episode_*.png      initial vs final hypothesis of chosen episodes (Fig. 2)"
echo "  $OUT/evaluation/results.json       all figures; bop/*.csv for bop_toolkit"
echo "  $SCORE/reliability.png        the pick-success score's calibration on held-out train images"
echo "  $RUN/cost_model.json          the cost model the agent was trained and evaluated with"
echo "  $CELL_RUN/learning_curve.png  the cell agent's training curve"
echo "  $OUT/cell/results.json             the cell pipeline: agent vs fixed ground-truth-free pipelines and oracle"
echo "  $OUT/replay/replay_check.png       through ROS vs in-process: success and operator time"
echo "  $OUT/replay_composed/replay_check.png  the same with the nodes composed in one process"
echo "  $OUT/replay/replay.mcap            the recorded bag (perception-config launch --bag ... --policy ... replays it)"
