"""Packaging metadata against the code: setup.py's install_requires and package.xml's dependencies
name exactly what perception_config imports; requirements.lock pins every line of requirements.txt
with hashes. Checked on the source (ast, xml), so a new import without its declaration fails here.
"""
from __future__ import annotations

import ast
import re
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "perception_config"

# Top-level module -> the pip distribution that provides it (where the names differ, and the rest).
IMPORT_TO_DIST = {
    "cv2": "opencv-contrib-python-headless", "yaml": "pyyaml", "open3d": "open3d-cpu", "mcap_ros2": "mcap-ros2-support",
    "numpy": "numpy", "scipy": "scipy", "tqdm": "tqdm", "matplotlib": "matplotlib", "mcap": "mcap",
    "rosbags": "rosbags", "trimesh": "trimesh", "gymnasium": "gymnasium", "torch": "torch",
    "safetensors": "safetensors", "zstandard": "zstandard", "lz4": "lz4", "pyarrow": "pyarrow",
    "ray": "ray",
}
# Top-level modules that are ROS 2 packages: declared in package.xml, provided by the ROS prefix.
ROS_PACKAGES = {"rclpy", "std_msgs", "geometry_msgs", "sensor_msgs", "builtin_interfaces", "rcl_interfaces",
                "perception_config_interfaces", "std_srvs", "visualization_msgs", "shape_msgs", "nav_msgs",
                "diagnostic_msgs", "action_msgs", "lifecycle_msgs", "tf2_msgs", "rosgraph_msgs", "foxglove_msgs"}
# package.xml entries that no import shows, each with its reason.
ROS_RUNTIME_ONLY = {"rmw_fastrtps_cpp": "the middleware the nodes and their Fast DDS profile are made for"}
# rosdep keys in package.xml -> the module they provide.
ROSDEP_TO_IMPORT = {"python3-numpy": "numpy", "python3-scipy": "scipy", "python3-opencv": "cv2",
                    "python3-yaml": "yaml", "python3-matplotlib": "matplotlib", "python3-tqdm": "tqdm"}


def third_party_imports() -> dict[str, set[str]]:
    """Top-level module -> files of perception_config that import it (anywhere in the file)."""
    found: dict[str, set[str]] = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                top = name.split(".")[0]
                if top not in sys.stdlib_module_names and top != "perception_config":
                    found.setdefault(top, set()).add(str(path.relative_to(ROOT)))
    return found


def setup_keyword(name: str) -> list[str]:
    """A list-of-strings keyword of the setup() call in setup.py."""
    tree = ast.parse((ROOT / "setup.py").read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and getattr(node.func, "id", "") == "setup":
            for kw in node.keywords:
                if kw.arg == name:
                    return [ast.literal_eval(e) for e in kw.value.elts]
    raise AssertionError(f"setup.py has no setup({name}=...)")


def dist_name(requirement: str) -> str:
    """Normalised distribution name of a requirement line ('ros-rclpy[fastrtps]==9.1.2' -> 'ros-rclpy')."""
    return re.sub(r"[-_.]+", "-", re.split(r"[\[<>=!~; ]", requirement.strip(), maxsplit=1)[0]).lower()


def requirement_lines(path: Path) -> list[str]:
    return [ln.strip() for ln in path.read_text().splitlines() if ln.strip() and not ln.lstrip().startswith("#")]


def package_xml_deps() -> dict[str, set[str]]:
    """Dependency tag -> names, of the root package.xml."""
    root = ET.parse(ROOT / "package.xml").getroot()
    out: dict[str, set[str]] = {}
    for tag in ("depend", "exec_depend", "build_depend", "test_depend", "buildtool_depend"):
        out[tag] = {e.text.strip() for e in root.findall(tag)}
    return out


def test_the_import_scan_sees_known_imports():
    imports = third_party_imports()
    ros_files = {"perception_config/ros/parameters.py", "perception_config/ros/configurator_node.py"}
    assert ros_files <= imports["rcl_interfaces"]
    assert "cv2" in imports and "numpy" in imports
    assert dist_name("ros-rclpy[fastrtps]==9.1.2") == "ros-rclpy" and dist_name("catkin_pkg==1.1.1") == "catkin-pkg"


def test_install_requires_names_every_third_party_import():
    imports = third_party_imports()
    unknown = sorted(set(imports) - set(IMPORT_TO_DIST) - ROS_PACKAGES)
    assert not unknown, (f"imports with no known distribution: {unknown} (in "
                         f"{[sorted(imports[u]) for u in unknown]}): add them to IMPORT_TO_DIST and install_requires")
    needed = {IMPORT_TO_DIST[m] for m in imports if m in IMPORT_TO_DIST}
    declared = {dist_name(r) for r in setup_keyword("install_requires")}
    missing = sorted(needed - declared)
    assert not missing, f"imported but missing from setup.py install_requires: {missing}"
    assert declared - needed == set(), f"in install_requires but never imported: {sorted(declared - needed)}"
    assert "torch==2.13.0" in setup_keyword("install_requires")


def test_package_xml_ros_dependencies_are_the_ros_imports():
    imports = {m for m in third_party_imports() if m in ROS_PACKAGES}
    deps = package_xml_deps()
    runtime = deps["depend"] | deps["exec_depend"]
    declared_ros = {d for d in runtime if not d.startswith("python3-")}
    missing = imports - declared_ros
    assert not missing, f"imported ROS packages missing from package.xml: {sorted(missing)}"
    extra = declared_ros - imports - set(ROS_RUNTIME_ONLY)
    assert not extra, f"package.xml declares ROS packages nothing imports: {sorted(extra)}"
    assert "std_srvs" not in runtime and "rcl_interfaces" in runtime


def test_package_xml_rosdep_keys_are_imported():
    imports = set(third_party_imports())
    deps = package_xml_deps()
    keys = {d for d in deps["depend"] | deps["exec_depend"] if d.startswith("python3-")}
    unknown = keys - set(ROSDEP_TO_IMPORT)
    assert not unknown, f"package.xml rosdep keys this test does not know: {sorted(unknown)}"
    unused = {k for k in keys if ROSDEP_TO_IMPORT[k] not in imports}
    assert not unused, f"package.xml rosdep keys for modules nothing imports: {sorted(unused)}"


def test_requirements_cover_install_requires_and_are_pinned():
    lines = requirement_lines(ROOT / "requirements.txt")
    unpinned = [ln for ln in lines if "==" not in ln]
    assert not unpinned, f"requirements.txt lines without an exact version (==X.Y.Z): {unpinned}"
    have = {dist_name(ln) for ln in lines}
    missing = {dist_name(r) for r in setup_keyword("install_requires")} - have
    assert not missing, f"install_requires not in requirements.txt: {sorted(missing)}"


def lock_entries() -> dict[str, tuple[str, int]]:
    """Normalised name -> (version, number of hashes) of requirements.lock."""
    out: dict[str, tuple[str, int]] = {}
    current = None
    for line in (ROOT / "requirements.lock").read_text().splitlines():
        m = re.match(r"^([A-Za-z0-9][A-Za-z0-9._-]*)==(\S+)", line)
        if m:
            current = dist_name(m.group(1))
            out[current] = (m.group(2), 0)
        elif current and "--hash=sha256:" in line:
            version, n = out[current]
            out[current] = (version, n + 1)
    return out


def test_lock_pins_every_requirement_with_hashes():
    lock = lock_entries()
    assert len(lock) > 100, f"requirements.lock has only {len(lock)} packages"
    stale = []
    for line in requirement_lines(ROOT / "requirements.txt"):
        name, version = dist_name(line), line.split("==", 1)[1].strip()
        locked = lock.get(name, ("absent", 0))[0]
        if locked.split("+")[0] != version:  # torch: the lock has the local version 2.13.0+cpu
            stale.append(f"{name}: requirements.txt {version}, requirements.lock {locked}")
    assert not stale, "requirements.lock is stale (run ./scripts/lock.sh): " + "; ".join(stale)
    unhashed = sorted(n for n, (_, count) in lock.items() if count == 0)
    assert not unhashed, f"requirements.lock entries without a hash: {unhashed}"
    assert lock["torch"][0] == "2.13.0+cpu", "torch must be the CPU wheel on this machine's disk"
    assert not [n for n in lock if n.startswith("nvidia-")], "a CUDA build of torch crept into the lock"

