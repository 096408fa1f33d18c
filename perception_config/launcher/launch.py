"""`perception-config launch`: the project's own launcher (no launch_ros in the PyPI wheels).

Starts ROS 2 nodes from their console scripts, each as its own OS process in its own session
(a terminal Ctrl-C reaches only the launcher, which forwards SIGINT once), streams every line
a node prints to the launcher's stdout as `[node_name] line` (and to `<log_dir>/<node>.log`),
stops them all on SIGINT/SIGTERM (SIGINT, 10 s, then SIGKILL), and reports a node that died:
`[launch] <node> died (exit code N)`, then stops the others (exit code 1). bag_replay_node may
finish (exit 0 at the end of its bag) without stopping the others.

This module only manages subprocesses: it never imports rclpy. The children get the project's
loopback defaults (perception_config.launcher.ros_environment) plus PYTHONUNBUFFERED=1.

From Python (the end-to-end tests, the demo):

    with Launcher([NodeSpec("generation_node", params={"models_dir": "/abs/models"})]) as launcher:
        launcher.wait_for_line("generation_node", "serving")
        ...  # talk to the node; leaving the block stops it (SIGINT, then SIGKILL)
"""
from __future__ import annotations

import collections
import fnmatch
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, TextIO

from .ros_environment import configure_ros_environment

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
# Nodes that may exit 0 on their own (bag_replay_node at the end of its bag).
FINITE_EXECUTABLES = ("bag_replay_node",)

DEFAULT_MODELS = Path("data/default/models")
FALLBACK_MODELS = Path("data/parts_models")
STOP_TIMEOUT = 10.0
REINSTALL_HINT = "run ./scripts/test.sh (or ./scripts/demo.sh) to set up and reinstall the package"


class MissingExecutable(FileNotFoundError):
    """A node's console script is not installed (the CLI turns this into exit code 2)."""


@dataclass
class NodeSpec:
    """One node to start: `name` prefixes its log lines, `executable` is a console script name
    (looked up next to the interpreter, then on PATH) or a path; `params` become `-p k:=v` after
    `--params-file` (so they win over the file)."""

    name: str
    executable: str | None = None
    params: dict[str, object] = field(default_factory=dict)
    params_file: str | os.PathLike | None = None
    may_finish: bool | None = None  # exit 0 on its own is "finished", not "died" (default: bag_replay_node)
    remaps: dict[str, str] = field(default_factory=dict)  # topic remappings, `-r from:=to`

    def __post_init__(self) -> None:
        if self.executable is None:
            self.executable = self.name
        if self.may_finish is None:
            self.may_finish = Path(str(self.executable)).name in FINITE_EXECUTABLES

    def arguments(self) -> list[str]:
        """The ROS arguments: `--ros-args [--params-file FILE] [-p name:=value ...] [-r from:=to ...]`."""
        args = ["--ros-args"]
        if self.params_file is not None:
            args += ["--params-file", str(self.params_file)]
        for key, value in self.params.items():
            args += ["-p", f"{key}:={param_value(value)}"]
        for source, target in self.remaps.items():
            args += ["-r", f"{source}:={target}"]
        return args

    def command(self, executable: str | None = None) -> list[str]:
        return [executable or str(self.executable), *self.arguments()]


def param_value(value: object) -> str:
    """A parameter value as the YAML scalar rcl parses from `-p name:=value`: strings are quoted
    whenever YAML would read them as something else ('' for empty, '123' for a digit string)."""
    import yaml

    if isinstance(value, os.PathLike):
        value = os.fspath(value)
    text = yaml.safe_dump(value, default_flow_style=True, width=float("inf"), allow_unicode=True)
    if text.endswith("\n...\n"):
        text = text[: -len("\n...\n")]
    return text.strip()


def find_executable(executable: str) -> str:
    """The path of a console script: a path as given, else next to this interpreter (the venv's
    bin/), else on PATH. Raises MissingExecutable naming it."""
    if os.sep in executable:
        if os.access(executable, os.X_OK) and Path(executable).is_file():
            return executable
        raise MissingExecutable(f"node executable {executable} does not exist or is not executable")
    beside = Path(sys.executable).parent / executable
    if beside.is_file() and os.access(beside, os.X_OK):
        return str(beside)
    found = shutil.which(executable)
    if found:
        return found
    raise MissingExecutable(
        f"console script {executable!r} not found (looked in {Path(sys.executable).parent} and on PATH): "
        f"{REINSTALL_HINT}"
    )


def node_environment(extra: dict[str, str] | None = None) -> dict[str, str]:
    """The environment of every child: this process's, the project's loopback ROS defaults
    (a value the user exported wins, e.g. ROS_DOMAIN_ID), PYTHONUNBUFFERED=1, then `extra`."""

    env = configure_ros_environment(dict(os.environ))
    env["PYTHONUNBUFFERED"] = "1"
    env.update(extra or {})
    return env


def _die_with_launcher() -> Callable[[], None] | None:
    """A preexec_fn giving the child SIGTERM when the launcher dies, even by SIGKILL (Linux
    PR_SET_PDEATHSIG), so no node outlives it. The signal follows the *thread* that started the
    child: call Launcher.start() from a thread that lives as long as the nodes (the main thread)."""
    if not sys.platform.startswith("linux"):
        return None
    import ctypes

    try:
        prctl = ctypes.CDLL(None, use_errno=True).prctl  # resolved before fork: the child only calls it
    except (OSError, AttributeError):
        return None
    parent, pr_set_pdeathsig, sigterm = os.getpid(), 1, int(signal.SIGTERM)

    def preexec() -> None:
        prctl(pr_set_pdeathsig, sigterm)
        if os.getppid() != parent:  # the launcher died before prctl took effect
            os._exit(1)

    return preexec


def describe_exit(code: int | None) -> str:
    if code is None:
        return "still running"
    if code < 0:
        try:
            return f"exit code {code}: killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"exit code {code}: killed by signal {-code}"
    return f"exit code {code}"


class _Child:
    def __init__(self, spec: NodeSpec, executable: str) -> None:
        self.spec = spec
        self.executable = executable
        self.proc: subprocess.Popen | None = None
        self.reader: threading.Thread | None = None
        self.log_file = None
        self.lines: collections.deque[str] = collections.deque(maxlen=2000)
        self.reported = False  # its own exit was announced (died / finished)
        self.killed = False


class Launcher:
    """Starts `nodes` as separate processes and supervises them.

    start(): resolve every executable first (MissingExecutable before anything starts), then
    start them all. wait(): block until a node exits on its own (died -> stop the rest, return 1;
    a finite node's exit 0 is "finished" and the rest keep running) or request_stop() is called
    (SIGINT/SIGTERM in the CLI: stop all, return 0 if all exited 0). stop(): SIGINT to every
    child's process group, up to `stop_timeout` s, SIGKILL stragglers, print each exit status;
    returns True when every node exited 0. A second request_stop() during stop() kills at once.
    With `die_with_launcher` (Linux) the nodes get SIGTERM if the launcher itself is killed.
    """

    def __init__(self, nodes: list[NodeSpec], log_dir: str | os.PathLike | None = None,
                 env: dict[str, str] | None = None, out: TextIO | None = None,
                 stop_timeout: float = STOP_TIMEOUT, die_with_launcher: bool = True) -> None:
        names = [n.name for n in nodes]
        if len(set(names)) != len(names):
            raise ValueError(f"node names must be unique, got {names}")
        self.nodes = list(nodes)
        self.log_dir = Path(log_dir) if log_dir is not None else None
        self.extra_env = dict(env or {})
        self.stop_timeout = stop_timeout
        self.die_with_launcher = die_with_launcher
        self._out = out
        self._children: dict[str, _Child] = {}
        self._write_lock = threading.Lock()
        self._lines_changed = threading.Condition()
        # Plain flags, not Events: request_stop() runs in signal handlers, which must not take locks.
        self._stop_requested = False
        self._kill_now = False
        self._stopped: bool | None = None

    # -- output ---------------------------------------------------------------------------
    def say(self, text: str) -> None:
        self._emit(f"[launch] {text}")

    def _emit(self, line: str) -> None:
        out = self._out if self._out is not None else sys.stdout
        with self._write_lock:
            try:
                out.write(line + "\n")
                out.flush()
            except (ValueError, OSError):  # stdout closed under us: keep supervising
                pass

    def _read(self, child: _Child) -> None:
        assert child.proc is not None and child.proc.stdout is not None
        prefix = f"[{child.spec.name}] "
        for raw in iter(child.proc.stdout.readline, b""):
            line = raw.decode("utf-8", errors="replace").rstrip("\r\n")
            self._emit(prefix + line)
            if child.log_file is not None:
                child.log_file.write(line + "\n")
                child.log_file.flush()
            with self._lines_changed:
                child.lines.append(line)
                self._lines_changed.notify_all()
        child.proc.stdout.close()

    # -- start ----------------------------------------------------------------------------
    def start(self) -> None:
        if self._children:
            raise RuntimeError("this launcher was already started")
        resolved = [(spec, find_executable(str(spec.executable))) for spec in self.nodes]
        env = node_environment(self.extra_env)
        preexec = _die_with_launcher() if self.die_with_launcher else None
        if self.log_dir is not None:
            self.log_dir.mkdir(parents=True, exist_ok=True)
        for spec, executable in resolved:
            child = _Child(spec, executable)
            if self.log_dir is not None:
                child.log_file = open(self.log_dir / f"{spec.name}.log", "w", encoding="utf-8")
            command = spec.command(executable)
            try:
                child.proc = subprocess.Popen(
                    command, env=env, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                    stderr=subprocess.STDOUT, start_new_session=True, preexec_fn=preexec,
                )
            except OSError:
                if child.log_file is not None:
                    child.log_file.close()
                self.stop()  # the ones already started
                raise
            self._children[spec.name] = child
            child.reader = threading.Thread(target=self._read, args=(child,), name=f"launch-{spec.name}", daemon=True)
            child.reader.start()
            self.say(f"started {spec.name} (pid {child.proc.pid}): {shlex.join([spec.executable, *command[1:]])}")

    # -- supervision ----------------------------------------------------------------------
    def request_stop(self) -> None:
        """Ask wait() to stop every node (safe from a signal handler); a second call kills at once."""
        if self._stop_requested:
            self._kill_now = True
        self._stop_requested = True

    def wait(self, timeout: float | None = None) -> int | None:
        """Supervise until a node dies (-> 1), every node has finished (-> 0) or a stop is requested
        (-> 0 if every node exited 0, else 1). None when `timeout` s passed first."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            if self._stop_requested:
                self.say("stopping all nodes")
                return 0 if self.stop() else 1
            for name, child in self._children.items():
                code = child.proc.poll() if child.proc else None
                if code is None or child.reported:
                    continue
                child.reported = True
                if child.reader is not None:  # its last lines (a traceback) come before the verdict
                    child.reader.join(2.0)
                if code == 0 and child.spec.may_finish:
                    self.say(f"{name} finished (exit code 0)")
                    continue
                self.say(f"{name} died ({describe_exit(code)})")
                self.stop()
                return 1
            if self._children and all(c.reported for c in self._children.values()):
                self.stop()
                return 0
            if deadline is not None and time.monotonic() >= deadline:
                return None
            time.sleep(0.1)

    def stop(self, timeout: float | None = None) -> bool:
        """SIGINT to every running node, wait up to `timeout` (default stop_timeout) s, SIGKILL
        the rest; print each node's exit status. True when every node exited 0. Idempotent."""
        if self._stopped is not None:
            return self._stopped
        timeout = self.stop_timeout if timeout is None else timeout
        children = [c for c in self._children.values() if c.proc is not None]
        for child in children:
            if child.proc.poll() is None:
                self._signal(child, signal.SIGINT)
        deadline = time.monotonic() + timeout
        while any(c.proc.poll() is None for c in children):
            if time.monotonic() >= deadline or self._kill_now:
                for child in children:
                    if child.proc.poll() is None:
                        child.killed = True
                        self._signal(child, signal.SIGKILL)
                break
            time.sleep(0.05)
        clean = True
        for child in children:
            try:
                code = child.proc.wait(10.0)
            except subprocess.TimeoutExpired:  # unkillable (uninterruptible sleep): report and move on
                code = None
            if child.reader is not None:
                child.reader.join(2.0)
            if child.log_file is not None:
                child.log_file.close()
            clean = clean and code == 0
            how = "killed with SIGKILL after not stopping on SIGINT" if child.killed else describe_exit(code)
            self.say(f"{child.spec.name}: {how}" if child.killed else f"{child.spec.name} exited ({how})")
        self._stopped = clean
        return clean

    @staticmethod
    def _signal(child: _Child, sig: signal.Signals) -> None:
        try:
            if os.getpgid(child.proc.pid) == child.proc.pid:
                os.killpg(child.proc.pid, sig)  # its own session: the node and anything it started
                return
        except (ProcessLookupError, PermissionError):
            pass
        if child.proc.poll() is None:
            child.proc.send_signal(sig)

    # -- inspection (tests, demo) ---------------------------------------------------------
    def pid(self, name: str) -> int:
        return self._children[name].proc.pid

    def returncode(self, name: str) -> int | None:
        return self._children[name].proc.poll()

    def running(self) -> list[str]:
        return [n for n, c in self._children.items() if c.proc is not None and c.proc.poll() is None]

    def output(self, name: str) -> list[str]:
        """The node's most recent output lines (without the prefix)."""
        with self._lines_changed:
            return list(self._children[name].lines)

    def wait_for_line(self, name: str, text: str, timeout: float = 30.0) -> str:
        """The first line of `name` containing `text`; AssertionError with its output when the
        node exits first or `timeout` s pass."""
        child = self._children[name]
        deadline = time.monotonic() + timeout
        with self._lines_changed:
            while True:
                for line in child.lines:
                    if text in line:
                        return line
                exited = child.proc.poll() is not None and not (child.reader and child.reader.is_alive())
                remaining = deadline - time.monotonic()
                if exited or remaining <= 0:
                    why = (f"exited ({describe_exit(child.proc.poll())})" if exited
                           else f"printed no such line within {timeout} s")
                    raise AssertionError(f"{name} {why} while waiting for {text!r}:\n" + "\n".join(child.lines))
                self._lines_changed.wait(min(remaining, 0.2))

    def __enter__(self) -> "Launcher":
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


# -- the command line's defaults -----------------------------------------------------------
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
                  say: Callable[[str], None] = print, remaps: dict[str, str] | None = None) -> list[NodeSpec]:
    """The NodeSpecs of `perception-config launch`, with every default resolved and every path
    absolute. Explicit options become `-p` parameters (they win over `params_file`); defaults
    are passed only where `params_file` does not set that parameter. `remaps` (topic: the
    camera driver's topic) go to every node that takes models and frames (the operator nodes
    and the configurator): a params file cannot remap."""
    cwd = Path(cwd or Path.cwd()).resolve()

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
        elif "policy" in params_file_sets(pfile, conf.name):
            say(f"policy: as set in {pfile}")
        else:
            newest = newest_policy(cwd, pipeline_ref)
            on = f"pipeline {pipeline}" if pipeline is not None else "the default pipeline"
            set_param(conf, "policy", str(newest) if newest else "", False)
            say(f"policy: {newest} (the newest runs/*/policy.safetensors trained on {on})" if newest
                else f"policy: none (no runs/*/policy.safetensors trained on {on} here): the configurator runs "
                     "the fixed pipeline")

    if "bag_replay" in names:
        replay = specs[names.index("bag_replay")]
        if bag is not None:
            set_param(replay, "bag", str(absolute(bag, "bag", is_dir=None)), True)  # a file or a rosbag2 folder
        if rate is not None:
            if not rate > 0:
                raise ValueError(f"--rate must be positive, got {rate}")
            set_param(replay, "rate", float(rate), True)
        info = readable_bag_info(replay.params.get("bag"))
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


def run(specs: list[NodeSpec], log_dir: str | os.PathLike | None = None) -> int:
    """Start `specs`, supervise until Ctrl-C/SIGTERM or a death; the command's exit code."""
    launcher = Launcher(specs, log_dir=log_dir)
    handled = (signal.SIGINT, signal.SIGTERM)
    previous = {sig: signal.signal(sig, lambda _signum, _frame: launcher.request_stop()) for sig in handled}
    try:
        launcher.start()  # MissingExecutable (exit 2) before anything starts
        return launcher.wait()
    finally:
        launcher.stop()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
