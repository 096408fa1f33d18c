"""Online-learning fixtures shared by the learning tests: the tiny dataset's env, its episodes
recorded as the configurator stores estimates, and a learn_dir made from them."""
from __future__ import annotations

from pathlib import Path

from rl_helpers import PIPELINE, pipeline_file

BASE_SEC = 1_700_000_000
# Each image of the tiny dataset is recorded as this many frames (stamps), each estimate with
# other seeds: as a cell sees the same bin again. The learner holds out a share of the frames
# (online/promotion_gate.py) and needs at least 5 check frames: 4 images alone would not do.
REPEATS = 6
RECORDED = 10_000  # the recorded frames' stamps start at stamp_ns(RECORDED): apart from those tests publish


def stamp_ns(i: int) -> int:
    return (BASE_SEC + i) * 1_000_000_000


def make_data(synthetic_dataset, tmp_path_factory) -> dict:
    """The tiny synthetic dataset with the learning tests' pipeline and env (cost-table time)."""
    from perception_config.rl.env import PerceptionConfigEnv

    pipe = pipeline_file(tmp_path_factory, PIPELINE)
    env = PerceptionConfigEnv(synthetic_dataset, pipe, time_mode="cost_table", min_visib_fract=0.3)
    return {"root": synthetic_dataset, "pipeline": pipe, "env": env}


def make_recorded(data, tmp_path_factory) -> Path:
    """Every episode of the tiny dataset played by the engineer's sequence, REPEATS times (each
    image recorded as REPEATS frames), stored as the configurator stores an estimate (an episode
    in the store + its frame with ground truth)."""
    from perception_config.agents import make_agent
    from perception_config.online.policy_learner import FRAMES
    from perception_config.rl.episode_loop import acting_seed, play_episode
    from perception_config.store.episode_store import STORE_NAME, StoreWriter, store_episode
    from perception_config.store.frames import save_frame

    env = data["env"]
    out = tmp_path_factory.mktemp("recorded")
    agent = make_agent("fixed", env)
    writer = StoreWriter(out / STORE_NAME, print)
    keys = sorted({(ek.scene_id, ek.im_id) for ek in env.source.episodes})
    n = len(env.source.episodes)
    for r in range(REPEATS):
        for j, ek in enumerate(env.source.episodes):
            stamp, seed = stamp_ns(RECORDED + r * len(keys) + keys.index((ek.scene_id, ek.im_id))), 1000 + r * n + j
            traj = play_episode(env, agent, {"episode": j, "lambda": 0.5, "episode_seed": seed}, acting_seed(seed))
            assert store_episode(writer, traj, source="configurator", agent="fixed", policy_version="v0000",
                                 episode_seed=seed, frame_stamp_ns=stamp, image_ids=False)
    for r in range(REPEATS):  # each frame once (the configurator saves a stamp once)
        for i, key in enumerate(keys):
            frame = env.source.frame(*key)
            save_frame(out / FRAMES, stamp_ns(RECORDED + r * len(keys) + i), frame,
                       {o.obj_id: o.gt for o in frame.objects})
    writer.close()
    return out


def record_like_the_configurator(learn_dir: Path, data, recorded: Path, sequence: list[str],
                                 env_settings: dict | None = None) -> int:
    """A learn_dir with the recorded estimates and version 0 = the fixed `sequence` (served with
    `env_settings`, default the env's); the count."""
    import shutil

    from perception_config.agents import make_agent, save_agent
    from perception_config.online.policy_learner import POLICIES, PolicyVersions

    shutil.copytree(recorded, learn_dir)
    env = data["env"]
    path = save_agent(make_agent("fixed", env, sequence=sequence), learn_dir / "start.json",
                      {"env_settings": env_settings or env.settings.to_json(), "pipeline": str(data["pipeline"])})
    assert PolicyVersions(learn_dir / POLICIES).promote(path, {"start": "fixed"}) == "v0000"
    return REPEATS * len(env.source.episodes)


# -- versions ------------------------------------------------------------------------------------
def learner_log(learn_dir: Path) -> str:
    p = learn_dir / "learner.log"
    return p.read_text() if p.exists() else ""


