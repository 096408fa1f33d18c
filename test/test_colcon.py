"""A ROS 2 workspace build with colcon (colcon-core + colcon-ros from PyPI, pinned in requirements.txt)
of a copy of the repository in a temporary workspace's src/, as docs/how-to/colcon.md
says: both packages are found, perception_config_interfaces is built once (its own
ament_cmake package from msg_defs/, against the ROS prefix of this venv's PyPI wheels) and not
bundled into install/perception_config, and a node started from install/ joins the ROS graph.
"""
from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from ros_helpers import ros_test_env

ROOT = Path(__file__).resolve().parents[1]
PYVER = f"python{sys.version_info.major}.{sys.version_info.minor}"
COLCON = Path(sys.executable).parent / "colcon"
# What a copy of the repository leaves out: environments, build outputs, data and caches.
NOT_COPIED = shutil.ignore_patterns(".venv*", ".git", "build", "install", "log", "__pycache__", "*.egg-info",
                                    ".pytest_cache", "data", "runs", "outputs", "*.logs")

pytestmark = [pytest.mark.ros, pytest.mark.skipif(not COLCON.exists(), reason=f"no colcon in {COLCON.parent}")]


def colcon_env() -> dict[str, str]:
    """The shell a user has after activating the venv: its ROS prefix (the PyPI wheels) on the
    ament and CMake prefix paths, its bin/ first on PATH."""
    env = ros_test_env()
    env["AMENT_PREFIX_PATH"] = sys.prefix
    env["CMAKE_PREFIX_PATH"] = sys.prefix
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    env.pop("PYTHONPATH", None)  # the node must find perception_config in install/, not in the checkout
    env.pop("PERCEPTION_CONFIG_SKIP_INTERFACES", None)
    return env


@pytest.fixture(scope="module")
def workspace(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A workspace with the repository copied into src/, built with docs/how-to/colcon.md's colcon command."""
    ws = tmp_path_factory.mktemp("colcon_ws")
    shutil.copytree(ROOT, ws / "src" / "perception_config", ignore=NOT_COPIED, symlinks=True)
    cmd = [str(COLCON), "build", "--base-paths", "src", "src/perception_config/msg_defs",
           "--cmake-args", f"-DPython3_EXECUTABLE={sys.executable}", "-DBUILD_TESTING=OFF"]
    env = colcon_env()
    if shutil.which("ninja", path=env["PATH"]) and "CMAKE_GENERATOR" not in env:
        # The same command and targets; CMake's Ninja generator instead of Makefiles: ~15 % less CPU
        # for the interfaces (no recursive make, no per-target dependency scans), as measured here.
        env["CMAKE_GENERATOR"] = "Ninja"
    if not any(k in env for k in ("MAKEFLAGS", "CMAKE_BUILD_PARALLEL_LEVEL")):
        # The same build, one compile per core. colcon gives the build tool -j<cores> -l<cores>, and
        # the load limit lets only one compile run at a time while the rest of the test run loads the
        # machine: 72 s instead of 43 s beside one busy process on 2 cores. A -j in MAKEFLAGS makes
        # colcon leave the job count to `cmake --build`, which takes CMAKE_BUILD_PARALLEL_LEVEL.
        cores = str(len(os.sched_getaffinity(0)))
        env["MAKEFLAGS"] = f"-j{cores}"
        env["CMAKE_BUILD_PARALLEL_LEVEL"] = cores
    t0 = time.monotonic()
    proc = subprocess.run(cmd, cwd=ws, env=env, capture_output=True, text=True, timeout=900)
    seconds = time.monotonic() - t0
    if proc.returncode != 0:
        logs = "\n".join(p.read_text()[-4000:] for p in sorted((ws / "log").rglob("stderr.log")))
        pytest.fail(f"colcon build failed ({proc.returncode}):\n{proc.stdout[-4000:]}\n{proc.stderr[-4000:]}\n{logs}")
    (ws / "build_output.txt").write_text(proc.stdout + proc.stderr)
    print(f"colcon build: {seconds:.1f} s")
    return ws


def test_colcon_finds_both_packages_and_builds_the_interfaces_first(workspace: Path):
    out = (workspace / "build_output.txt").read_text()
    finished = [ln.split()[2] for ln in out.splitlines() if ln.startswith("Finished <<< ")]
    assert finished == ["perception_config_interfaces", "perception_config"], out


def test_the_interfaces_are_built_once_in_their_own_prefix(workspace: Path):
    install = workspace / "install"
    prefix = install / "perception_config_interfaces"
    generated = prefix / "lib" / PYVER / "site-packages" / "perception_config_interfaces"
    assert (generated / "srv" / "__init__.py").is_file() and (generated / "msg" / "__init__.py").is_file()
    assert len(list((prefix / "lib").glob("libperception_config_interfaces__*.so"))) >= 8
    assert (prefix / "share" / "perception_config_interfaces" / "srv" / "EstimatePose.srv").is_file()
    bundled = [str(p.relative_to(install))
               for p in (install / "perception_config").rglob("*perception_config_interfaces*")]
    assert not bundled, f"install/perception_config carries a second copy of the interfaces: {bundled[:5]}"


def test_perception_config_installs_as_an_ament_python_package(workspace: Path):
    prefix = workspace / "install" / "perception_config"
    assert (prefix / "share" / "ament_index" / "resource_index" / "packages" / "perception_config").is_file()
    assert (prefix / "share" / "perception_config" / "package.xml").is_file()
    for script in ("generation_node", "refinement_node", "scoring_node", "pick_node", "configurator_node",
                   "bag_replay_node"):
        assert (prefix / "lib" / "perception_config" / script).is_file(), script  # where `ros2 run` looks
    assert (prefix / "lib" / PYVER / "site-packages" / "perception_config" / "config").is_dir()


def sourced(workspace: Path, command: str) -> list[str]:
    """A shell command run after `. install/setup.sh` (what a user of the workspace does; colcon-core
    writes the sh scripts, colcon-bash would add setup.bash)."""
    return ["sh", "-c", f". '{workspace / 'install' / 'setup.sh'}' && {command}"]


def test_a_sourced_workspace_imports_both_packages_from_install(workspace: Path):
    code = ("import perception_config, perception_config_interfaces.srv as s; "
            "print(perception_config.__file__); print(s.__file__); print(s.EstimatePose.Request())")
    proc = subprocess.run(sourced(workspace, f"'{sys.executable}' -c '{code}'"), cwd=workspace / "install",
                          env=colcon_env(), capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-3000:]
    lines = proc.stdout.splitlines()
    assert lines[0].startswith(str(workspace / "install" / "perception_config" / "lib")), lines[0]
    assert lines[1].startswith(str(workspace / "install" / "perception_config_interfaces" / "lib")), lines[1]
    assert "EstimatePose_Request(" in lines[2]


def test_a_node_started_from_install_joins_the_graph(workspace: Path, ros_node):
    script = workspace / "install" / "perception_config" / "lib" / "perception_config" / "scoring_node"
    name = f"colcon_scoring_{os.getpid()}"
    log = workspace / "scoring_node.log"
    with open(log, "w") as out:
        proc = subprocess.Popen(sourced(workspace, f"exec '{script}' --ros-args -r __node:={name}"),
                                env=colcon_env(), stdout=out, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 30.0
        wanted = ["perception_config_interfaces/srv/ScoreHypothesis"]
        services: dict = {}
        while wanted not in services.values():  # the node, then its service of our interface type
            assert proc.poll() is None, f"scoring_node from install/ exited {proc.returncode}:\n{log.read_text()}"
            assert time.monotonic() < deadline, (f"scoring_node's ScoreHypothesis service not on the graph after "
                                                 f"30 s (its services: {services}):\n{log.read_text()}")
            time.sleep(0.2)
            if name in ros_node.get_node_names():
                services = dict(ros_node.get_service_names_and_types_by_node(name, "/"))
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def test_a_plain_colcon_build_finds_the_root_package_and_uses_the_prefix_interfaces(tmp_path: Path):
    """`colcon build` without base paths: the crawl stops at the repository root (the product card fixes
    package.xml there), so only perception_config is found; a prefix that provides the interfaces (here
    the venv's pip install; on a distro a built workspace) is used, nothing is compiled or bundled, and
    the setup says so. (Without such a prefix it compiles msg_defs/ into its own prefix, as pip does.)"""
    ws = tmp_path / "ws"
    shutil.copytree(ROOT, ws / "src" / "perception_config", ignore=NOT_COPIED, symlinks=True)
    proc = subprocess.run([str(COLCON), "build", "--event-handlers", "console_direct+"], cwd=ws, env=colcon_env(),
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    started = [ln.split()[2] for ln in proc.stdout.splitlines() if ln.startswith("Starting >>> ")]
    assert started == ["perception_config"], proc.stdout[-3000:]
    assert f"perception_config_interfaces provided by {sys.prefix}" in proc.stdout + proc.stderr
    assert not list((ws / "install" / "perception_config").rglob("*perception_config_interfaces*"))
    code = ("import perception_config, perception_config_interfaces.srv as s; "
            "print(perception_config.__file__); print(s.EstimatePose.Request())")
    run = subprocess.run(sourced(ws, f"'{sys.executable}' -c '{code}'"), cwd=ws / "install", env=colcon_env(),
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr[-3000:]
    assert run.stdout.startswith(str(ws / "install" / "perception_config" / "lib")), run.stdout
