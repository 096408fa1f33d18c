"""Start project nodes as separate OS processes and talk to them with a real rclpy node."""
from __future__ import annotations

import atexit
import os
import random
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

VENV_BIN = Path(sys.executable).parent
REPO = Path(__file__).resolve().parents[1]


def ros_test_env() -> dict[str, str]:
    """The environment for node processes of this test session: loopback, a domain of its own."""
    env = dict(os.environ)
    env["ROS_DOMAIN_ID"] = os.environ["ROS_DOMAIN_ID"]
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"]
    env["PYTHONUNBUFFERED"] = "1"
    return env


# Test domains: clear of 0 (ROS's default) and 42 (the project's), within the 0..101 that Linux's
# ephemeral ports leave to Fast DDS.
TEST_DOMAINS = range(60, 101)


def pick_domain_id() -> int:
    """A domain id unlikely to collide with other processes on a shared machine."""
    return random.SystemRandom().choice(TEST_DOMAINS)


def worker_domain_id(base: int, worker: str) -> int:
    """The domain of pytest-xdist worker `worker` ("gw0", "gw1", ...) of a session whose domain is
    `base`: the next ids of TEST_DOMAINS after `base`, so the workers of one session never share a
    domain, nor use the controller's (a developer's own `base` included)."""
    index = int(worker.removeprefix("gw"))
    return TEST_DOMAINS[(base - TEST_DOMAINS[0] + 1 + index) % len(TEST_DOMAINS)]


_STARTED: list["NodeProcess"] = []


@atexit.register
def _kill_leftovers() -> None:
    """No node outlives the test session, whatever failed on the way."""
    for node in _STARTED:
        if node.proc.poll() is None:
            node.proc.kill()


class NodeProcess:
    """A node started from its console script; stopped with SIGINT, then SIGKILL."""

    def __init__(self, script: str, params: dict[str, object] | None = None, log_dir: Path | None = None,
                 remap: dict[str, str] | None = None, own_group: bool = False) -> None:
        """`own_group`: the node leads a process group of its own (its learner process joins it), as
        under systemd or a container runtime, so `signal_group` reaches them all."""
        args = [str(VENV_BIN / script), "--ros-args"]
        for key, value in (params or {}).items():
            args += ["-p", f"{key}:={value}"]
        for old, new in (remap or {}).items():
            args += ["-r", f"{old}:={new}"]
        self.log = (log_dir or Path("/tmp")) / f"{script}-{os.getpid()}-{time.time_ns()}.log"
        self._log_file = open(self.log, "w")
        self.proc = subprocess.Popen(args, env=ros_test_env(), stdout=self._log_file, stderr=subprocess.STDOUT,
                                     start_new_session=own_group)
        self._interrupted = False
        _STARTED.append(self)

    def output(self) -> str:
        if not self._log_file.closed:
            self._log_file.flush()
        return self.log.read_text()

    def alive(self) -> bool:
        return self.proc.poll() is None

    def signal_group(self, sig: signal.Signals, timeout: float) -> tuple[int | None, float]:
        """Send `sig` to the node's process group (started with own_group); (exit code or None if it
        was still running after `timeout` s, seconds it took). A node still running is killed."""
        start = time.monotonic()
        os.killpg(self.proc.pid, sig)
        try:
            code: int | None = self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            code = None
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait(5)
        return code, time.monotonic() - start

    def interrupt(self) -> None:
        """SIGINT (Ctrl-C), once: a later stop() waits for the node without a second one."""
        if self.proc.poll() is None and not self._interrupted:
            self.proc.send_signal(signal.SIGINT)
            self._interrupted = True

    def stop(self, timeout: float = 10.0) -> int:
        if self.proc.poll() is None:
            self.interrupt()
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        self._log_file.close()
        return self.proc.returncode


def stop_all(nodes: dict[str, NodeProcess], timeout: float = 10.0) -> dict[str, int]:
    """Stop nodes together: SIGINT to all, then each one's exit code (stop: SIGKILL after `timeout`),
    so their shutdowns overlap instead of following one another."""
    for node in nodes.values():
        node.interrupt()
    return {name: node.stop(timeout) for name, node in nodes.items()}


def wait_until(cond, timeout: float, what: str) -> None:
    """Poll `cond()` until true; AssertionError "<what> within <timeout> s" after `timeout` s."""
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"{what} within {timeout} s")
        time.sleep(0.05)


def wait_for_service(node, client, timeout: float = 20.0, process: NodeProcess | None = None) -> None:
    """Wait for a service; fail at once with the node's output when its process died."""
    deadline = time.monotonic() + timeout
    while not client.wait_for_service(timeout_sec=0.2):
        if process is not None and not process.alive():
            raise AssertionError(f"{process.log.name} died (exit {process.proc.returncode}):\n{process.output()}")
        if time.monotonic() > deadline:
            raise AssertionError(f"service {client.srv_name} did not appear within {timeout} s")


def publish_when_matched(node, publisher, msg, subscribers: int = 1, timeout: float = 20.0) -> None:
    """Publish once `subscribers` subscriptions have matched (a message sent before is lost)."""
    import rclpy

    deadline = time.monotonic() + timeout
    while publisher.get_subscription_count() < subscribers:
        if time.monotonic() > deadline:
            raise AssertionError(f"only {publisher.get_subscription_count()} of {subscribers} subscribers matched "
                                 f"{publisher.topic_name} within {timeout} s")
        rclpy.spin_once(node, timeout_sec=0.05)
    publisher.publish(msg)


def record_estimates(node, request, depth: int = 10) -> tuple[list, list]:
    """Lists that collect the configurator's published estimates (perception/trace OperatorTrace,
    perception/pose PoseStamped) on the test's node, unsubscribed when the test ends: the session
    node stays clean."""
    from geometry_msgs.msg import PoseStamped
    from perception_config_interfaces.msg import OperatorTrace

    traces: list = []
    poses: list = []
    subs = [node.create_subscription(OperatorTrace, "perception/trace", traces.append, depth),
            node.create_subscription(PoseStamped, "perception/pose", poses.append, depth)]
    request.addfinalizer(lambda: [node.destroy_subscription(s) for s in subs])
    return traces, poses


def call(node, client, request, timeout: float = 10.0):
    """Call a service from the test's node and spin until the answer (or fail after `timeout`)."""
    import rclpy

    future = client.call_async(request)
    rclpy.spin_until_future_complete(node, future, timeout_sec=timeout)
    if not future.done():
        raise AssertionError(f"no answer from {client.srv_name} within {timeout} s")
    return future.result()


class GoalRun:
    """One goal sent to an action server from the test's node: its acceptance, feedback, result."""

    def __init__(self, node, client, goal) -> None:
        self.node = node
        self.feedback: list = []
        self.sent = time.monotonic()
        self._accept = client.send_goal_async(goal, feedback_callback=lambda m: self.feedback.append(m.feedback))
        self.handle = None
        self._result = None

    def spin_until(self, cond, timeout: float, what: str) -> None:
        import rclpy

        deadline = time.monotonic() + timeout
        while not cond():
            if time.monotonic() > deadline:
                raise AssertionError(f"{what} within {timeout} s")
            rclpy.spin_once(self.node, timeout_sec=0.02)

    def accepted(self, timeout: float = 10.0) -> bool:
        self.spin_until(self._accept.done, timeout, "no goal response")
        self.handle = self._accept.result()
        return bool(self.handle.accepted)

    def cancel(self) -> None:
        self.handle.cancel_goal_async()

    def result(self, timeout: float = 30.0):
        """(status, result message) once the result has arrived."""
        if self._result is None:
            self._result = self.handle.get_result_async()
        self.spin_until(self._result.done, timeout, "no result")
        res = self._result.result()
        return res.status, res.result


class LaunchCli:
    """`python -m perception_config.cli launch ...` (this checkout's code) with its output collected."""

    def __init__(self, args: list[str], cwd: Path) -> None:
        env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
        # Its own process group, like a shell job: killpg below is a terminal's Ctrl-C.
        self.proc = subprocess.Popen([sys.executable, "-m", "perception_config.cli", "launch", *args], cwd=cwd, env=env,
                                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                     start_new_session=True)
        self.lines: list[str] = []
        self._reader = threading.Thread(target=lambda: self.lines.extend(iter(self.proc.stdout.readline, "")),
                                        daemon=True)
        self._reader.start()

    def wait_for(self, pattern: str, timeout: float = 30.0) -> re.Match:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            for line in list(self.lines):
                if m := re.search(pattern, line):
                    return m
            if self.proc.poll() is not None and not self._reader.is_alive():
                break
            time.sleep(0.05)
        raise AssertionError(f"no line matching {pattern!r}:\n{self.output()}")

    def finish(self, timeout: float = 30.0) -> int:
        try:
            code = self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            raise AssertionError(f"the launcher did not exit within {timeout} s:\n{self.output()}") from None
        self._reader.join(5)
        return code

    def output(self) -> str:
        return "".join(self.lines)

    def stop(self, timeout: float = 30.0) -> int:
        """Ctrl-C to its group (as a terminal sends), then SIGKILL after `timeout` s; the exit code."""
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGINT)
        try:
            return self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            os.killpg(self.proc.pid, signal.SIGKILL)
            return self.proc.wait(10)
        finally:
            self._reader.join(5)
