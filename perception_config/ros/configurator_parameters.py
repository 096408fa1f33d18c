"""The configurator node's parameters (configurator_node.py), each with its description, range
and choices: what `ros2 param describe configurator_node <name>` and the reference show.

All but the two version pins are read at start-up (read-only); `policy_version` and
`score_version` may be set at run time (`ros2 param set configurator_node policy_version v0002`).
"""
from __future__ import annotations

import math

from ..agents.fixed import DEFAULT_SEQUENCE
from ..core.geometry import LAMBDA_MAX
from ..online.promotion_gate import CHECK_EPISODES
from ..rl.settings import MAX_OPS_LIMIT
from ..store.episode_store import PICK_SOURCES
from .camera_frames import CAMERA_QOS
from .parameters import INT_MAX, NodeParameter
from .request_queue import MAX_REQUEST_QUEUE

LEARN_STARTS = ("policy", "fixed", "untrained")  # learn_start's choices

PARAMETERS = (
    NodeParameter("policy", "", "policy file (.safetensors) from `perception-config train` (\"\" = the fixed "
                  "pipeline `fixed_sequence`)", read_only=True),
    NodeParameter("fixed_sequence", list(DEFAULT_SEQUENCE), "the engineer's sequence used without a policy",
                  read_only=True),
    NodeParameter("pipeline", "", "pipeline YAML (\"\" = the policy's, else the built-in default); must be the "
                  "operator nodes' pipeline", read_only=True),
    NodeParameter("models_dir", "", "BOP models folder (the object's diameter is part of the agent's state); "
                  "required", read_only=True),
    NodeParameter("max_ops", 0, "operators per estimate (0 = the policy's training value, else 10)",
                  limits=(0, MAX_OPS_LIMIT), read_only=True),
    NodeParameter("max_ops_cap", 50, "operators per estimate at most, whatever the policy file or request says",
                  limits=(1, INT_MAX), read_only=True),
    NodeParameter("estimate_timeout", 10.0, "seconds from a request's arrival to its answer (> 0), queueing "
                  "included: checked before the estimate starts and before each operator, and bounding each "
                  "operator call's wait. An estimate that reaches it while queued, or while waiting for an "
                  "operator's answer, answers success=false; one that reaches it between two operators answers "
                  "success=true, picked=false with the hypothesis so far. Every such message begins "
                  "\"estimate_timeout (X s) reached\"",
                  limits=(0.0, math.inf), read_only=True),
    NodeParameter("request_queue", 10, "estimate requests that may wait while one runs; one more is answered at "
                  "once with success=false \"busy: N requests queued (request_queue=M)\"",
                  limits=(0, MAX_REQUEST_QUEUE), read_only=True),
    NodeParameter("noise_lambda", 0.5, "lambda of simulated initialisation when a request does not give one",
                  limits=(0.0, LAMBDA_MAX), read_only=True),
    NodeParameter("operator_timeout", 10.0, "seconds to wait for one operator call (> 0)",
                  limits=(0.0, math.inf), read_only=True),
    NodeParameter("fused_scoring", True, "the generation and refinement nodes score their own result in the same "
                  "call (true: one round trip per action); false: every scoring is a call to scoring_node "
                  "(ros_operators.py)", read_only=True),
    NodeParameter("auto", False, "estimate every new camera frame (seen on `camera/camera_info`): the objects in "
                  "`auto_objects`, or, when that is empty, every object of the frame's replayed ground truth (a test "
                  "bench). Frames that arrive while an estimate runs are skipped, except the latest",
                  read_only=True),
    NodeParameter("auto_objects", [""], "(auto) the objects estimated in every new frame (empty = those of the "
                  "frame's replayed ground truth)", read_only=True),
    NodeParameter("auto_every_frame", False, "(auto) the frames that arrive while an estimate runs are all "
                  "estimated in turn (the last 64), not only the latest", read_only=True),
    NodeParameter("camera_qos", "reliable", "QoS of the camera subscriptions: reliable, or sensor_data "
                  "(best effort)", read_only=True, choices=CAMERA_QOS),
    NodeParameter("use_depth", True, "true: the camera gives depth; false: an RGB-only camera (the operator nodes' "
                  "use_depth false): the actions that need depth are masked (info[\"action_mask\"]), the agent never "
                  "chooses them", read_only=True),
    NodeParameter("publish_debug", True, "the live view (debug_view.py): `perception/debug_image` (the frame with "
                  "the final hypothesis's outline, object id, scores and the operator trace) and `perception/markers` "
                  "(the model's mesh at the pose), each built only while it has a subscriber", read_only=True),
    NodeParameter("debug_image_max_width", 640, "the debug image is scaled down to this width (0 = full size)",
                  limits=(0, INT_MAX), read_only=True),
    NodeParameter("marker_max_triangles", 500, "the marker mesh is decimated to at most this many triangles",
                  limits=(1, INT_MAX), read_only=True),
    NodeParameter("episode_store", "", "an episodes.sqlite file (store/episode_store.py) to which every estimate's "
                  "episode is appended (frame stamp, object, lambda, generator, every operator with its scores, pose, "
                  "times and outcome, the pick's result, the policy version); \"\" = off: a node has no run folder of "
                  "its own, so where the store lives is the launcher's choice (replay-check puts it in its output "
                  "folder). Written with synchronous=FULL (a robot's pick outlives a power cut). A store that cannot "
                  "be written (full disk, locked by another process for more than 0.5 s, corrupt, not a store) is one "
                  "error log line per estimate (repeats counted); the estimate is answered as usual", read_only=True),
    NodeParameter("pick_source", "simulated", "who answers the pick_node's picks, recorded with each pick: "
                  "simulated, or robot (pick_node's robot_service set)", read_only=True, choices=PICK_SOURCES),
    NodeParameter("learn", False, "online learning (ros/learning.py, online/policy_learner.py): every estimate is "
                  "stored with its frame in `learn_dir`, a learner process trains candidates and promotes those that "
                  "beat the serving version on a replay of stored episodes; the serving policy is swapped between "
                  "estimates", read_only=True),
    NodeParameter("learn_dir", "", "(learn) the learning state: episodes.sqlite (the store, unless episode_store is "
                  "given), frames/, policies/ (v0000..., versions.json), learner.log; required with learn",
                  read_only=True),
    NodeParameter("learn_start", "policy", "(learn) version 0 when learn_dir has none: policy (the policy file, "
                  "else the fixed pipeline), fixed or untrained (a fresh pg policy)", read_only=True,
                  choices=LEARN_STARTS),
    NodeParameter("learn_margin", 0.05, "(learn) a candidate is promoted only if its mean cost on the held-out check "
                  "frames is below (1 - margin) x the serving version's, besides lower at 95 % confidence with "
                  "success not lower (online/promotion_gate.py); below 1", limits=(0.0, 1.0), read_only=True),
    NodeParameter("learn_every", 20, "(learn) new stored estimates between two candidates",
                  limits=(1, INT_MAX), read_only=True),
    NodeParameter("learn_train_episodes", 200,
                  "(learn) training episodes per cycle (the learner continues its weights while one version serves)",
                  limits=(0, INT_MAX), read_only=True),
    NodeParameter("learn_check_episodes", CHECK_EPISODES,
                  "(learn) a candidate's replay check: at most the newest this many stored episodes of the "
                  "held-out check frames (never trained on); at least 15 on 5 frames are needed",
                  limits=(1, INT_MAX), read_only=True),
    NodeParameter("policy_version", "", "(learn) pin a kept version at run time (`ros2 param set ... "
                  "policy_version v0002`); \"\" = the newest promoted; an unknown version is refused with the kept "
                  "ones"),
    NodeParameter("score_version", "", "(learn, a pipeline with pick_success) the same for the learned pick-success "
                  "score: versions in `learn_dir`/pick_success/ (online/score_learner.py), followed by the operator "
                  "nodes whose `pick_success_versions` names that folder"),
)
