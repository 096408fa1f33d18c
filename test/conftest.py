"""Shared fixtures: the real LM-O samples (skipped when ../shared is absent), the tiny synthetic
dataset, a procedural box model, and the rclpy client node of cross-process ROS tests."""
from __future__ import annotations

import os
import signal
import tempfile
import warnings
from pathlib import Path
from typing import Callable

import pytest

from frames import box_mesh
from ros_helpers import pick_domain_id, worker_domain_id

# The repo and ../shared are siblings: /work/main and /work/shared.
LMO_ROOT = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "lmo"
LMO_RGB_ROOT = LMO_ROOT.with_name("lmo-rgb")

# With pytest-xdist (scripts/test.sh) this file runs in the controller, whose environment the
# workers inherit, then in each worker ("gw0", "gw1", ...); without it, once.
WORKER = os.environ.get("PYTEST_XDIST_WORKER")

# Prepared per-model tables (the ppf generator's) go to a folder of this session, not the user's
# cache. The workers share the controller's: entries are written atomically (vision/disk_cache.py).
if WORKER and os.environ.get("PERCEPTION_CONFIG_TEST_CACHE"):
    os.environ["PERCEPTION_CONFIG_CACHE"] = os.environ["PERCEPTION_CONFIG_TEST_CACHE"]
else:
    _CACHE = tempfile.TemporaryDirectory(prefix="perception_config_test_cache_")
    os.environ["PERCEPTION_CONFIG_CACHE"] = os.environ["PERCEPTION_CONFIG_TEST_CACHE"] = _CACHE.name

# ROS processes of this test session get a domain of their own (set before rclpy loads), and each
# worker one of its own: two workers' nodes must not answer each other's requests.
os.environ.setdefault("PERCEPTION_CONFIG_TEST_DOMAIN", str(pick_domain_id()))
if WORKER:
    os.environ["PERCEPTION_CONFIG_TEST_DOMAIN"] = str(worker_domain_id(int(os.environ["PERCEPTION_CONFIG_TEST_DOMAIN"]),
                                                                       WORKER))
os.environ["ROS_DOMAIN_ID"] = os.environ["PERCEPTION_CONFIG_TEST_DOMAIN"]
# Ray's temporary folder (its sessions and the address of the last cluster started, which a bare
# ray.init() joins) one per worker: a worker's local Ray must not join another worker's cluster.
# Short, under /tmp: Ray's socket paths must stay under 108 characters.
if WORKER:
    _RAY_TMP = tempfile.TemporaryDirectory(prefix=f"ray-{WORKER}-", dir="/tmp", ignore_cleanup_errors=True)
    os.environ["RAY_TMPDIR"] = _RAY_TMP.name
# The project's loopback defaults (perception_config.launcher.ros_environment), whatever the shell exported.
os.environ["FASTDDS_DEFAULT_PROFILES_FILE"] = str(Path(__file__).resolve().parents[1] / "perception_config" / "ros"
                                                  / "fastdds_profile.xml")
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "SYSTEM_DEFAULT"

# Tests stop their child processes with SIGINT (Ctrl-C). A suite started as a background job
# of a non-interactive shell inherits SIGINT ignored, and so would every child: catch it here,
# so children start with the default disposition (a caught signal is reset on exec).
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


def _shared_data(root: Path, what: str) -> Path:
    """`root`, a BOP folder of ../shared; the test is skipped in a clone without it."""
    if not (root / "models" / "models_info.json").exists():
        pytest.skip(f"{what} not available at {root}")
    return root


@pytest.fixture(scope="session")
def lmo_root() -> Path:
    """The real BOP LM-O sample (one RGB-D frame)."""
    return _shared_data(LMO_ROOT, "real LM-O sample")


@pytest.fixture(scope="session")
def lmo_dataset(lmo_root: Path):
    """The LM-O sample as a BopDataset (test split: scene 2, image 3)."""
    from perception_config.datasets.bop import BopDataset

    return BopDataset(lmo_root, "test")


@pytest.fixture(scope="session")
def lmo_frame(lmo_dataset):
    """The sample's one real RGB-D frame (scene 2, image 3) with the 8 object models, loaded once.
    Shared by the whole session, so its images are read-only: a test that wants to change one
    works on a copy."""
    frame = lmo_dataset.load_frame(2, 3)
    for array in (frame.rgb, frame.depth, frame.K):
        array.flags.writeable = False
    return frame


@pytest.fixture(scope="session")
def lmo_rgb_root() -> Path:
    """Twenty real LM-O RGB frames without depth (BOP layout)."""
    return _shared_data(LMO_RGB_ROOT, "real LM-O RGB frames")


@pytest.fixture(scope="session")
def lmo_rgb_frames(lmo_rgb_root: Path) -> list:
    """Two real LM-O RGB photographs (images 36 and 58, no depth) with their models, loaded once;
    read-only."""
    from perception_config.datasets.bop import BopDataset

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the annotations' near-rotations are projected, with a warning
        ds = BopDataset(lmo_rgb_root, use_depth=False)
        frames = [ds.load_frame(*ds.image_keys()[i]) for i in (4, 9)]
    for frame in frames:
        frame.rgb.flags.writeable = False
    return frames


@pytest.fixture(scope="session")
def synthetic_dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The tiny synthetic BOP dataset (2 scenes x 2 images, seed 0), generated once per session
    and shared with rl_helpers.make_env. Tests only read it."""
    from rl_helpers import tiny_dataset

    return tiny_dataset(tmp_path_factory)


@pytest.fixture(scope="session")
def tiny_pg_policy(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A pg policy trained briefly on the tiny dataset (cost-table time: fast, deterministic), once
    per session: test_cell_sim and test_replay_check serve it through the nodes. Tests only read it."""
    from perception_config.learning.training import train
    from perception_config.rl.settings import EnvSettings
    from rl_helpers import pipeline_file, tiny_dataset

    settings = EnvSettings(time_mode="cost_table", lambda_range=(0.2, 0.8), max_ops=5)
    return train(tiny_dataset(tmp_path_factory), "pg", tmp_path_factory.mktemp("policy") / "run", 16,
                 settings=settings, seed=0, pipeline=pipeline_file(tmp_path_factory), progress=False, workers=1,
                 agent_kwargs={"batch_episodes": 8})


@pytest.fixture(scope="session")
def make_box() -> Callable[..., "object"]:
    """Factory: an ObjectModel of a box (metres) with the given size and obj_id."""
    from perception_config.core.models import make_model

    def make(size: tuple[float, float, float] = (0.1, 0.06, 0.04), obj_id: int = 1):
        v, f = box_mesh(size)
        return make_model(obj_id, v, f, n_points=2000)

    return make


@pytest.fixture(scope="session")
def ros_node():
    """One rclpy context and node for the test process (the client side of cross-process tests)."""
    import rclpy

    from perception_config.launcher.ros_environment import configure_ros_environment

    configure_ros_environment()  # the loopback defaults before rclpy.init
    rclpy.init()
    node = rclpy.create_node(f"pytest_client_{os.getpid()}")
    yield node
    node.destroy_node()
    rclpy.try_shutdown()


# The files that take a quarter of a minute or more on 2 cores, longest first (measured with
# --durations=0). They run first: pytest-xdist hands whole files to the workers in collection
# order (scripts/test.sh: --dist loadfile --no-loadscope-reorder), so that the last files to
# start are short ones and no worker waits idle for one long file at the end.
LONG_FILES = ("test_ros_nodes", "test_training_signals", "test_cell_sim", "test_colcon", "test_online_learning",
              "test_learning_signals", "test_ray_cluster", "test_launch", "test_candidates", "test_replay_check",
              "test_score_learning", "test_pick_success", "test_ray_workers",
              "test_training_validation", "test_evaluation", "test_study", "test_ppf", "test_agents",
              "test_ros_lifecycle", "test_bop_toolkit", "test_bench_real", "test_cost_model", "test_best_static",
              "test_resting_pose", "test_ros_replay")


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """A test that talks to ROS nodes (it takes the ros_node fixture) is a `ros` test, marked or not,
    so `-m "not ros"` leaves out every test that starts nodes (test_score_learning's were missed).
    The files of LONG_FILES go first, in its order; the others follow as collected."""
    for item in items:
        if "ros_node" in getattr(item, "fixturenames", ()) and item.get_closest_marker("ros") is None:
            item.add_marker(pytest.mark.ros)
    rank = {name: i for i, name in enumerate(LONG_FILES)}
    items.sort(key=lambda item: rank.get(item.path.stem, len(LONG_FILES)))  # stable: each file's own order stays
