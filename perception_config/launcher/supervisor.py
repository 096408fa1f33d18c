"""The process supervisor of `perception-config launch`, the project's own launcher (no launch_ros
in the PyPI wheels).

Starts ROS 2 nodes from their console scripts, each as its own OS process in its own session
(a terminal Ctrl-C reaches only the launcher, which forwards SIGINT once), streams every line
a node prints to the launcher's stdout as `[node_name] line` (and to `<log_dir>/<node>.log`),
stops them all on SIGINT/SIGTERM (SIGINT, 10 s, then SIGKILL), and reports a node that died:
`[launch] <node> died (exit code N)`, then stops the others (exit code 1). bag_replay_node may
finish (exit 0 at the end of its bag) without stopping the others.

This module only manages subprocesses: it never imports rclpy. The children get the project's
loopback defaults (perception_config.launcher.ros_environment) plus PYTHONUNBUFFERED=1.

The nodes and their parameters come from launcher/resolution.py. From Python (the end-to-end
tests, the demo):

    with Launcher([NodeSpec("generation_node", params={"models_dir": "/abs/models"})]) as launcher:
        launcher.wait_for_line("generation_node", "serving")
        ...  # talk to the node; leaving the block stops it (SIGINT, then SIGKILL)
"""
from __future__ import annotations

import collections
import os
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

# Nodes that may exit 0 on their own (bag_replay_node at the end of its bag).
FINITE_EXECUTABLES = ("bag_replay_node",)
# Nodes that `composed` runs in one process (ros/composed.py), and the name of that process.
COMPOSABLE_EXECUTABLES = ("generation_node", "refinement_node", "scoring_node", "pick_node", "configurator_node")
CELL = "perception_cell"
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
    # the cell process of a composed launch: its nodes, {"executable", "args"} each (ros/composed.py)
    composed: list[dict[str, object]] | None = None

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
        if self.composed is not None:  # the cell process: its nodes and their arguments (ros/composed.py)
            import json

            return [executable or str(self.executable), "--nodes", json.dumps(self.composed)]
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

    `composed`: the nodes of COMPOSABLE_EXECUTABLES run in one process, `perception_cell`
    (ros/composed.py), each with the arguments it would get alone; the others (bag_replay_node)
    stay separate. The inspection methods take node names as before: a composed node's lines
    are the cell's lines that name it, its exit code the cell's.
    """

    def __init__(self, nodes: list[NodeSpec], log_dir: str | os.PathLike | None = None,
                 env: dict[str, str] | None = None, out: TextIO | None = None,
                 stop_timeout: float = STOP_TIMEOUT, die_with_launcher: bool = True, composed: bool = False) -> None:
        names = [n.name for n in nodes]
        if len(set(names)) != len(names):
            raise ValueError(f"node names must be unique, got {names}")
        self.requested = list(nodes)
        self.composed_names: list[str] = []
        if composed:
            inside = [n for n in nodes if Path(str(n.executable)).name in COMPOSABLE_EXECUTABLES]
            if CELL in names:
                raise ValueError(f"a node may not be named {CELL} in a composed launch")
            if inside:
                self.composed_names = [n.name for n in inside]
                cell = NodeSpec(CELL, executable=CELL, composed=[
                    {"executable": Path(str(n.executable)).name, "args": n.arguments()} for n in inside])
                nodes = [cell, *[n for n in nodes if n not in inside]]
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

    @property
    def stop_requested(self) -> bool:
        return self._stop_requested

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
    def _child(self, name: str) -> _Child:
        return self._children[CELL if name in self.composed_names else name]

    def _mine(self, name: str, line: str) -> bool:
        """Whether a line of the node's process is the node's (a composed node's lines name it)."""
        return name not in self.composed_names or f"[{name}]" in line

    def pid(self, name: str) -> int:
        return self._child(name).proc.pid

    def returncode(self, name: str) -> int | None:
        return self._child(name).proc.poll()

    def running(self) -> list[str]:
        """The names of the nodes whose process runs (every composed node while the cell runs)."""
        names = [n.name for n in self.requested]
        return [n for n in names if (c := self._child(n)).proc is not None and c.proc.poll() is None]

    def output(self, name: str) -> list[str]:
        """The node's most recent output lines (without the prefix)."""
        with self._lines_changed:
            return [line for line in self._child(name).lines if self._mine(name, line)]

    def wait_for_line(self, name: str, text: str, timeout: float = 30.0) -> str:
        """The first line of `name` containing `text`; AssertionError with its output when the
        node exits first or `timeout` s pass."""
        child = self._child(name)
        deadline = time.monotonic() + timeout
        with self._lines_changed:
            while True:
                for line in child.lines:
                    if text in line and self._mine(name, line):
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


def run(specs: list[NodeSpec], log_dir: str | os.PathLike | None = None, composed: bool = False,
        bring_up: Callable[["Launcher"], bool] | None = None) -> int:
    """Start `specs` (composed: launcher.composed), then `bring_up(launcher)` if given (drives the
    managed nodes to active; False: they could not be, exit 1), supervise until Ctrl-C/SIGTERM or
    a death; the command's exit code."""
    launcher = Launcher(specs, log_dir=log_dir, composed=composed)
    handled = (signal.SIGINT, signal.SIGTERM)
    previous = {sig: signal.signal(sig, lambda _signum, _frame: launcher.request_stop()) for sig in handled}
    try:
        launcher.start()  # MissingExecutable (exit 2) before anything starts
        if bring_up is not None and not bring_up(launcher):
            if not launcher.stop_requested:
                launcher.say("stopping all nodes")
            launcher.stop()
            return 1
        return launcher.wait()
    finally:
        launcher.stop()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
