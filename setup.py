"""perception_config: an ament_python package whose install also compiles msg_defs/.

`pip install --no-build-isolation .` (what scripts/setup_env.sh runs) builds the interfaces
package `perception_config_interfaces` with rosidl against the ROS 2 prefix of the running
interpreter (the PyPI ROS wheels install a whole ROS prefix into the venv root) and installs:
  - the generated Python package into site-packages,
  - its eight `libperception_config_interfaces__rosidl_*.so` into <prefix>/lib,
  - its share/ (the .msg/.srv files and the ament index entry) into <prefix>/share.
A failed interface build stops the install with CMake's output: pip then installs nothing.

In a colcon workspace msg_defs/ is its own ament_cmake package (README: "colcon workspace"). When
another prefix on AMENT_PREFIX_PATH already provides perception_config_interfaces (colcon's
install/perception_config_interfaces, or a ROS installation), the interfaces are not compiled
again and not bundled: the package then depends on that prefix, as package.xml says.
PERCEPTION_CONFIG_SKIP_INTERFACES=1 always skips them, =0 always builds them.
"""
from __future__ import annotations

import glob
import os
import shutil
import subprocess
import sys
from pathlib import Path

from setuptools import find_packages, setup
from setuptools.command.build_py import build_py

PACKAGE = "perception_config"
INTERFACES = "perception_config_interfaces"
HERE = Path(__file__).resolve().parent


def _ros_prefix() -> Path:
    """The prefix holding the ROS 2 build tools: AMENT_PREFIX_PATH entries, then sys.prefix."""
    candidates = [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    candidates.append(sys.prefix)
    for c in candidates:
        if (Path(c) / "share" / "rosidl_default_generators").is_dir():
            return Path(c)
    raise SystemExit(
        "perception_config: cannot compile msg_defs/: no ROS 2 prefix with rosidl_default_generators "
        f"found in AMENT_PREFIX_PATH or {sys.prefix}. Install the build requirements first "
        "(pip install -r requirements.txt) and build without isolation: "
        "pip install --no-build-isolation ."
    )


def _run(cmd: list[str], env: dict[str, str], log: Path) -> None:
    """Run a build step; on failure show its output (the compiler's error) and stop."""
    with open(log, "w") as f:
        proc = subprocess.run(cmd, env=env, stdout=f, stderr=subprocess.STDOUT)
    if proc.returncode != 0:
        sys.stderr.write(log.read_text()[-20000:])
        raise SystemExit(f"perception_config: interface build step failed: {' '.join(cmd)} (log: {log})")


def interfaces_provider() -> Path | None:
    """A prefix on AMENT_PREFIX_PATH, other than this interpreter's own (which the install may be
    replacing), whose ament index registers perception_config_interfaces; None when there is none."""
    own = Path(sys.prefix).resolve()
    for entry in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep):
        if not entry or Path(entry).resolve() == own:
            continue
        if (Path(entry) / "share" / "ament_index" / "resource_index" / "packages" / INTERFACES).is_file():
            return Path(entry)
    return None


class BuildPyWithInterfaces(build_py):
    """build_py that first compiles msg_defs/ with rosidl and stages the results, unless another
    prefix provides the interfaces already (see the module docstring)."""

    def run(self) -> None:
        skip = os.environ.get("PERCEPTION_CONFIG_SKIP_INTERFACES", "")
        provider = interfaces_provider() if skip == "" else None
        if provider is not None:
            print(f"{INTERFACES} provided by {provider}: not compiled again or bundled", flush=True)
        elif skip != "1":
            self._build_interfaces()
        super().run()

    def _build_interfaces(self) -> None:
        if shutil.which("cmake") is None:
            raise SystemExit("perception_config: cmake is required to compile msg_defs/ (apt-get install cmake)")
        prefix = _ros_prefix()
        # A build dir kept between installs makes a rebuild with unchanged msg_defs/ a no-op.
        build_dir = HERE / "build" / "interfaces-cmake"
        stage = HERE / "build" / "interfaces-install"
        build_dir.mkdir(parents=True, exist_ok=True)
        if stage.exists():
            shutil.rmtree(stage)
        env = dict(os.environ)
        env["AMENT_PREFIX_PATH"] = str(prefix)
        env["CMAKE_PREFIX_PATH"] = str(prefix)
        env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{prefix / 'bin'}{os.pathsep}{env.get('PATH', '')}"
        generator = ["-G", "Ninja"] if shutil.which("ninja") else []
        cache = build_dir / "CMakeCache.txt"
        if cache.exists() and "Ninja" not in cache.read_text() and generator:
            generator = []  # keep the generator the cache was made with
        self.announce("compiling msg_defs/ into perception_config_interfaces", level=2)
        _run(
            ["cmake", "-S", str(HERE / "msg_defs"), "-B", str(build_dir), *generator,
             f"-DPython3_EXECUTABLE={sys.executable}", f"-DCMAKE_INSTALL_PREFIX={stage}",
             "-DBUILD_TESTING=OFF", "-DCMAKE_BUILD_TYPE=Release"],
            env, build_dir / "configure.log",
        )
        jobs = str(max(1, min(4, os.cpu_count() or 1)))
        _run(["cmake", "--build", str(build_dir), "-j", jobs], env, build_dir / "build.log")
        _run(["cmake", "--install", str(build_dir)], env, build_dir / "install.log")

        pyver = f"python{sys.version_info.major}.{sys.version_info.minor}"
        generated = stage / "lib" / pyver / "site-packages" / INTERFACES
        if not (generated / "__init__.py").is_file():
            raise SystemExit(f"perception_config: the interface build produced no Python package at {generated}")
        dest = Path(self.build_lib) / INTERFACES
        if dest.exists():
            shutil.rmtree(dest)
        shutil.copytree(generated, dest, ignore=shutil.ignore_patterns("__pycache__", "*.c"))

        libs = sorted(glob.glob(str(stage / "lib" / f"lib{INTERFACES}__*.so")))
        if len(libs) < 8:
            raise SystemExit(f"perception_config: expected 8 interface libraries in {stage / 'lib'}, found {len(libs)}")
        data = self.distribution.data_files
        data.append(("lib", libs))
        share = stage / "share"
        for root, _dirs, files in os.walk(share):
            if files:
                rel = Path(root).relative_to(stage)
                data.append((str(rel), [str(Path(root) / f) for f in files]))


setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(include=[PACKAGE, f"{PACKAGE}.*"]),
    package_data={PACKAGE: ["config/*.yaml", "config/pick_success/*.safetensors", "config/pick_success/*.json",
                            "ros/*.xml"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
    ],
    python_requires=">=3.10",
    # Every third-party import of perception_config (test/test_packaging.py checks). The ROS 2
    # packages (rclpy, the message packages) come from the ROS prefix and are declared in package.xml;
    # requirements.lock pins the exact versions set-up installs, ROS wheels included.
    install_requires=[
        "numpy>=1.26", "scipy>=1.11", "open3d-cpu==0.20.0", "opencv-contrib-python-headless>=4.8", "pyyaml>=6",
        "tqdm>=4.60", "matplotlib>=3.7", "mcap>=1.1", "mcap-ros2-support>=0.5", "rosbags>=0.10",
        "trimesh>=4.0", "zstandard>=0.22", "lz4>=4.3", "gymnasium>=1.0", "torch==2.13.0", "safetensors>=0.4",
        "pyarrow>=14", "ray==2.58.0",
    ],
    # The documentation (docs/): `pip install .[docs]`, then `sphinx-build docs docs/_build/html`.
    extras_require={"docs": ["sphinx>=8", "myst-parser>=4"]},
    zip_safe=False,
    maintainer="perception_config developers",
    maintainer_email="dev@perception-config.invalid",
    description="A ROS 2 perception service for robotic picking that configures itself.",
    license="Apache-2.0",
    cmdclass={"build_py": BuildPyWithInterfaces},
    entry_points={
        "console_scripts": [
            "perception-config = perception_config.cli:main",
            "generation_node = perception_config.ros.generation_node:main",
            "refinement_node = perception_config.ros.refinement_node:main",
            "scoring_node = perception_config.ros.scoring_node:main",
            "pick_node = perception_config.ros.pick_node:main",
            "configurator_node = perception_config.ros.configurator_node:main",
            "bag_replay_node = perception_config.ros.bag_replay_node:main",
            "perception_cell = perception_config.ros.composed:main",
        ],
    },
)
