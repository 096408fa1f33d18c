"""The nodes `perception-config launch` starts, resolved: the short names of --nodes, every
default (the models folder, a bag's camera topics and what bag_replay_node waits for) and every
path made absolute, as NodeSpecs for the supervisor (launcher/supervisor.py). An explicit option
wins over a ROS params file, which wins over the defaults. The configurator's policy has no
default: --policy FILE, --policy none (its fixed pipeline), or a params file that sets `policy`
or `learn` (the learn directory's versions serve); else launch refuses, naming the newest
policy trained on the pipeline as the candidate."""
from __future__ import annotations

import collections
import fnmatch
import os
import re
from pathlib import Path
from typing import Callable

from .supervisor import NodeSpec

# Short names accepted by --nodes and the console script each one runs.
NODE_EXECUTABLES = {
    "generation": "generation_node",
    "refinement": "refinement_node",
    "scoring": "scoring_node",
    "pick": "pick_node",
    "configurator": "configurator_node",
    "bag_replay": "bag_replay_node",
}
OPERATOR_NODES = ("generation", "refinement", "scoring", "pick")
DEFAULT_NODES = (*OPERATOR_NODES, "configurator")
# Nodes that take models_dir and pipeline.
MODEL_NODES = (*OPERATOR_NODES, "configurator")
# What each launched node subscribes to among a bag's topics: bag_replay_node waits for them
# (wait_for) so that a short bag is not replayed before the nodes serve (about 4 s after start).
CAMERA_TOPICS = ("camera/color/image_raw", "camera/depth/image_raw", "camera/camera_info")
NODE_SUBSCRIPTIONS = {
    "generation": (*CAMERA_TOPICS, "perception/ground_truth"),
    "refinement": CAMERA_TOPICS,
    "scoring": CAMERA_TOPICS,
    "pick": (*CAMERA_TOPICS, "perception/ground_truth"),
}
REPLAY_WAIT_TIMEOUT = 60.0  # s: the nodes start in about 4 s, more on a loaded machine

DEFAULT_MODELS = Path("data/default/models")
FALLBACK_MODELS = Path("data/parts_models")


def parse_nodes(text: str) -> list[str]:
    """`generation,refinement` (or `generation_node,...`) -> short names, validated."""
    names = []
    for item in text.split(","):
        item = item.strip()
        if not item:
            continue
        short = item.removesuffix("_node")
        if short not in NODE_EXECUTABLES:
            raise ValueError(f"unknown node {item!r}; choose from {', '.join(NODE_EXECUTABLES)}")
        if short not in names:
            names.append(short)
    if not names:
        raise ValueError("no nodes given")
    return names


def newest_policy(cwd: Path, pipeline: str | None = None) -> Path | None:
    """The most recently modified runs/*/policy.safetensors under `cwd` trained on `pipeline`
    (as training records it: a shipped pipeline's name, a file's absolute path, None for the
    default), so that `launch --pipeline cell` does not start the configurator with a policy of
    another action set; unreadable files are passed over."""
    from ..agents.policy_io import policy_info

    def trained_on(path: Path) -> str | None | bool:
        try:
            recorded = (policy_info(path).get("extra") or {}).get("pipeline")
        except Exception:  # noqa: BLE001 - a broken file is not a candidate
            return False
        return None if recorded == "default" else recorded

    candidates = [p for p in (cwd / "runs").glob("*/policy.safetensors") if p.is_file() and trained_on(p) == pipeline]
    return max(candidates, key=lambda p: p.stat().st_mtime) if candidates else None


def default_models(cwd: Path, say: Callable[[str], None]) -> Path:
    """data/default/models (demo.sh's synthetic dataset); when absent, the procedural part models
    written once into data/parts_models."""
    default = cwd / DEFAULT_MODELS
    if (default / "models_info.json").is_file():
        return default
    fallback = cwd / FALLBACK_MODELS
    if not (fallback / "models_info.json").is_file():
        from ..datasets.parts import write_models

        write_models(fallback)
        say(f"models: {DEFAULT_MODELS} not found (./scripts/demo.sh synthesises it); "
            f"wrote the procedural part models to {fallback}")
    else:
        say(f"models: {DEFAULT_MODELS} not found (./scripts/demo.sh synthesises it); "
            f"using the procedural part models in {fallback}")
    return fallback


def params_file_sets(params_file: Path | None, node_name: str) -> set[str]:
    """Parameter names a ROS params YAML sets for `node_name` (`node_name:`, `/node_name:`, `/**:`,
    other wildcards); defaults are not passed for these, so the file wins over defaults while
    explicit options (passed as -p) win over the file."""
    if params_file is None:
        return set()
    import yaml

    data = yaml.safe_load(Path(params_file).read_text()) or {}
    if not isinstance(data, dict):
        raise ValueError(f"{params_file}: a ROS params file maps node names to {{ros__parameters: ...}}")
    names: set[str] = set()
    for key, body in data.items():
        pattern = str(key).lstrip("/")
        if not (pattern in ("**", "*") or fnmatch.fnmatchcase(node_name, pattern.replace("**", "*"))
                or fnmatch.fnmatchcase(node_name, pattern.rsplit("/", 1)[-1].replace("**", "*"))):
            continue
        params = (body or {}).get("ros__parameters", {}) if isinstance(body, dict) else {}
        names.update(str(k) for k in (params or {}))
    return names


def resolve_nodes(nodes: list[str] | None = None, models: str | os.PathLike | None = None,
                  pipeline: str | os.PathLike | None = None, policy: str | None = None,
                  bag: str | os.PathLike | None = None, rate: float | None = None,
                  params_file: str | os.PathLike | None = None, cwd: str | os.PathLike | None = None,
                  say: Callable[[str], None] = print, remaps: dict[str, str] | None = None,
                  warn: Callable[[str], None] | None = None) -> list[NodeSpec]:
    """The NodeSpecs of `perception-config launch`, with every default resolved and every path
    absolute. Explicit options become `-p` parameters (they win over `params_file`); defaults
    are passed only where `params_file` does not set that parameter. `remaps` (topic: the
    camera driver's topic) go to every node that takes models and frames (the operator nodes
    and the configurator): a params file cannot remap. `say` tells what was resolved; `warn`
    (default: `say` with "warning: ") gets the one line of a bag that yields no frame
    (`bag_frames_problem`), before any node starts."""
    cwd = Path(cwd or Path.cwd()).resolve()
    warn = warn or (lambda text: say(f"warning: {text}"))

    def absolute(p: str | os.PathLike, what: str, is_dir: bool | None = False) -> Path:
        """`p` made absolute; it must be a folder (is_dir), a file (not is_dir) or either (None)."""
        path = (cwd / Path(p).expanduser()).resolve()
        if not (path.exists() if is_dir is None else path.is_dir() if is_dir else path.is_file()):
            raise FileNotFoundError(f"{what} {p} does not exist" + (" (or is not a folder)" if is_dir else ""))
        return path

    names = list(nodes) if nodes is not None else list(DEFAULT_NODES)
    if bag is not None and "bag_replay" not in names:
        names.append("bag_replay")
    pfile = absolute(params_file, "params file") if params_file is not None else None
    specs = [NodeSpec(NODE_EXECUTABLES[n], params_file=pfile) for n in names]

    def set_param(spec: NodeSpec, key: str, value: object, explicit: bool) -> None:
        if explicit or key not in params_file_sets(pfile, spec.name):
            spec.params[key] = value

    model_specs = [s for n, s in zip(names, specs) if n in MODEL_NODES]
    if model_specs:
        if models is not None:
            models_dir = absolute(models, "models folder", is_dir=True)
            if not (models_dir / "models_info.json").is_file():
                raise FileNotFoundError(f"models folder {models} has no models_info.json (a BOP models/ folder)")
            for s in model_specs:
                set_param(s, "models_dir", str(models_dir), True)
        elif not all("models_dir" in params_file_sets(pfile, s.name) for s in model_specs):
            models_dir = default_models(cwd, say)
            say(f"models: {models_dir}")
            for s in model_specs:
                set_param(s, "models_dir", str(models_dir), False)
    pipeline_ref = None  # as a policy's training records it
    if pipeline is not None:
        from ..blocks.pipeline import shipped_pipelines

        shipped = not (cwd / Path(pipeline)).exists() and str(pipeline) in shipped_pipelines()
        pipeline_ref = str(pipeline) if shipped else str(absolute(pipeline, "pipeline"))
        if pipeline_ref == "default":
            pipeline_ref = None
        for s in model_specs:
            set_param(s, "pipeline", str(pipeline) if shipped else pipeline_ref, True)

    for source, target in (remaps or {}).items():
        if not source or not target or ":=" in source or ":=" in target:
            raise ValueError(f"a remap is FROM:=TO with two topic names, got {source!r}:={target!r}")
        for s in model_specs:
            s.remaps[source] = target

    if "configurator" in names:
        conf = specs[names.index("configurator")]
        if policy is not None:
            value = "" if policy.lower() == "none" else str(absolute(policy, "policy"))
            set_param(conf, "policy", value, True)
            say(f"policy: {value or 'none (the configurator runs the fixed pipeline)'}")
        elif params_file_sets(pfile, conf.name) & {"policy", "learn"}:  # learning: learn_dir's versions serve
            say(f"policy: as set in {pfile}")
        else:  # never a policy nobody chose (the newest file by date could be anyone's experiment)
            newest = newest_policy(cwd, pipeline_ref)
            on = f"pipeline {pipeline}" if pipeline is not None else "the default pipeline"
            found = (f"the newest trained on {on} here is {newest}" if newest
                     else f"there is no runs/*/policy.safetensors trained on {on} here")
            raise ValueError(f"no --policy: name the policy the configurator serves (--policy FILE), or --policy none "
                             f"for its fixed pipeline; launch does not choose one ({found})")

    if "bag_replay" in names:
        replay = specs[names.index("bag_replay")]
        if bag is not None:
            set_param(replay, "bag", str(absolute(bag, "bag", is_dir=None)), True)  # a file or a rosbag2 folder
        if rate is not None:
            if not rate > 0:
                raise ValueError(f"--rate must be positive, got {rate}")
            set_param(replay, "rate", float(rate), True)
        info = readable_bag_info(replay.params.get("bag"))
        problem = bag_frames_problem(info, remapped=bool(remaps))
        if problem:
            warn(problem)
        remaps = camera_remaps(info)
        if remaps:
            layout = info["frame_topics"].get("layout") or "chosen by name"
            say(f"the bag's camera topics ({layout}): the nodes subscribe to "
                + ", ".join(f"{target} as {source}" for source, target in remaps.items()))
            for n, s in zip(names, specs):
                if n in MODEL_NODES:
                    s.remaps.update(remaps)
        user_waits = params_file_sets(pfile, replay.name) & {"wait_for", "wait_for_subscribers", "topics"}
        waits = replay_waits(names, info, remaps)
        if waits and not user_waits:
            replay.params["wait_for"] = waits
            set_param(replay, "wait_timeout", REPLAY_WAIT_TIMEOUT, False)
        if info is not None and isinstance(info.get("frame_topics"), dict) and "depth" not in info["frame_topics"]:
            say("the bag has no depth topic: the nodes run RGB-only (use_depth false; depth actions masked)")
            for n, s in zip(names, specs):
                if n in MODEL_NODES:
                    set_param(s, "use_depth", False, False)
    return specs


def readable_bag_info(bag: str | None) -> dict | None:
    """`bag info` of the bag, or None when no bag is given or it cannot be read (bag_replay_node
    then reports the bag itself)."""
    if not bag:
        return None
    from ..datasets.bag.info import bag_info

    try:
        return bag_info(bag)
    except Exception:  # noqa: BLE001 - any unreadable bag: the replay node names the problem
        return None


def bag_frames_problem(info: dict | None, remapped: bool = False, shown: int = 10) -> str | None:
    """Why the nodes will receive no camera frame from a bag (its `bag_info`), as one line naming
    the bag, what is missing and the topics it has (the first `shown`); None when it yields
    frames, or cannot be read (bag_replay_node then names the problem). A frame is a colour image
    with the colour camera's camera_info (and the depth image of an RGB-D recording): from images
    alone the nodes build nothing. `remapped`: --remap names the camera topics, so a bag whose
    camera topics launch cannot choose is not reported."""
    from ..datasets.bag.topics import CAMERA_INFO, IMAGE_TYPES

    if info is None or info.get("frames"):
        return None
    topics = info.get("topics") or []
    types = {t["type"] for t in topics}
    chosen = info.get("frame_topics")
    if not types & set(IMAGE_TYPES):
        missing = "it has no image topic (sensor_msgs/msg/Image or CompressedImage)"
    elif CAMERA_INFO not in types:
        missing = f"it has images but no {CAMERA_INFO} topic, and a frame needs the colour camera's camera_info"
    elif isinstance(chosen, dict):
        counts = {t["topic"]: t["count"] for t in topics}
        empty = [chosen[role] for role in ("color", "depth", "camera_info") if chosen.get(role)
                 and not counts.get(chosen[role])]
        missing = f"no messages on {', '.join(empty)}"
    elif remapped:
        return None
    else:
        why = str(info.get("frame_topics_error", "")).removeprefix(f"{info.get('path')}: ")
        missing = (f"launch cannot choose its camera topics ({why}) and the nodes subscribe to "
                   f"{', '.join(CAMERA_TOPICS)}: name the bag's with --remap FROM:=TO")
    listed = ", ".join(f"{t['topic']} ({t['type'].rsplit('/', 1)[-1]}, {t['count']} msgs)" for t in topics[:shown])
    more = f", ... ({len(topics)} in all)" if len(topics) > shown else ""
    return (f"bag {info.get('path')} yields no frames, the nodes will receive no camera frame: {missing}; "
            f"topics: {listed or 'none'}{more}")


def replayed_topic(topic: str) -> str:
    """The topic bag_replay_node publishes a bag topic on: a compressed image
    (`<image>/compressed`, `<image>/compressedDepth`) decoded under its raw name."""
    return re.sub(r"/(compressed|compressedDepth)$", "", topic)


def camera_remaps(info: dict | None) -> dict[str, str]:
    """Remappings of the nodes' camera subscriptions (CAMERA_TOPICS) to the topics the replay
    publishes for the bag's colour, depth and camera_info (a driver layout such as RealSense's
    `/camera/camera/color/image_raw`): empty when the bag uses the nodes' names or its camera
    topics cannot be chosen."""
    chosen = info.get("frame_topics") if info else None
    if not isinstance(chosen, dict):
        return {}
    remaps = {}
    for ours, role in zip(CAMERA_TOPICS, ("color", "depth", "camera_info")):
        topic = chosen.get(role)
        if isinstance(topic, str) and topic and replayed_topic(topic).lstrip("/") != ours:
            remaps[ours] = replayed_topic(topic)
    return remaps


def replay_waits(names: list[str], info: dict | None, remaps: dict[str, str] | None = None) -> list[str]:
    """bag_replay_node's default `wait_for`: "topic:count" for each topic the replay publishes
    for the bag (its `bag_info`) that launched nodes subscribe to (through `remaps`), count =
    how many of them do. Empty without a readable bag."""
    if info is None:
        return []
    remaps = remaps or {}
    in_bag = {replayed_topic(t["topic"]).lstrip("/") for t in info["topics"]}
    subscribed = (remaps.get(t, t).lstrip("/") for n in names for t in NODE_SUBSCRIPTIONS.get(n, ()))
    counts = collections.Counter(t for t in subscribed if t in in_bag)
    return [f"{topic}:{count}" for topic, count in counts.items()]
