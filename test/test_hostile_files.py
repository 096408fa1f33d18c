"""Hostile files: crafted and fuzzed policy files, BOP scenes and bags (nothing read from disk is trusted).

Every input either loads or raises the module's documented error (PolicyError, BopFormatError,
BagFormatError), within a bounded time and memory. The fuzz tests are seeded and stop after
FUZZ_SECONDS each; they assert that a minimum number of inputs was tried."""
from __future__ import annotations

import json
import resource
import struct
import sys
import time
import warnings
import zlib
from pathlib import Path

import numpy as np
import pytest

from perception_config.agents import EnvSpec, PolicyError, load_agent, make_agent, save_agent
from perception_config.agents.policy_io import CHECKSUM_KEY, read_file, write_file
from perception_config.datasets.bag import BagFormatError, bag_info, read_bag, write_frames
from perception_config.datasets.bag.type_names import check_type_name
from perception_config.datasets.bop import BopDataset
from perception_config.datasets.errors import BopFormatError
from perception_config.datasets.image_header import MAX_IMAGE_PIXELS
from perception_config.util.safe_json import loads_limited

sys.path.insert(0, str(Path(__file__).parent))
from test_bag import make_frame  # noqa: E402
from test_bop import make_tiny_dataset  # noqa: E402

FUZZ_SECONDS = 1.5  # per fuzz test (each tries 750-2200 inputs in that time here, far above its minimum)
MAX_INPUT_SECONDS = 2.0  # one input, loaded or refused
MAX_RSS_GROWTH_KB = 300 * 1024  # peak RSS growth over a whole fuzz test

SPEC = EnvSpec(action_names=("icp_coarse", "icp_fine", "pick"), action_kinds=("refinement", "refinement", "pick"),
               observation_layout=("step", "score:a", "score:b"), max_ops=6)


def _maxrss_kb() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss


def _policy(tmp_path: Path, kind: str = "pg", **kw) -> Path:
    agent = make_agent(kind, SPEC, **kw)
    return save_agent(agent, tmp_path / f"{kind}.policy", {"env_settings": {"max_ops": 6}})


def _rewrite_meta(path: Path, fn, checksum: bool = True) -> None:
    """Change a policy file's metadata (the tensors as they are); a new checksum unless told not to."""
    meta, tensors = read_file(path)
    fn(meta)
    meta.pop(CHECKSUM_KEY, None)
    write_file(path, meta, tensors)
    if not checksum:
        from safetensors.numpy import save

        meta2, tensors2 = read_file(path)
        meta2.pop(CHECKSUM_KEY)
        if tensors2:
            path.write_bytes(save(tensors2, metadata={"perception_config": json.dumps(meta2)}))
        else:
            path.write_text(json.dumps(meta2))


# --------------------------------------------------------------------------- policy files: crafted


@pytest.mark.parametrize("change, match", [
    (lambda m: m["hparams"].update(hidden=10**12), r"hidden = 1000000000000 is outside its bounds"),
    (lambda m: m["hparams"].update(hidden=3e6), r"hidden = 3000000.0 is outside its bounds"),
    (lambda m: m["hparams"].update(hidden="32"), r"hidden must be an integer"),
    (lambda m: m["hparams"].update(env="x"), r"unknown hyper-parameters \['env'\]"),
    (lambda m: m.update(env="a string"), r"'env' must be a JSON object"),
    (lambda m: m.update(agent=["pg"]), r"'agent' must be a name"),
    (lambda m: m.update(hparams=[1]), r"'hparams' must be a JSON object"),
    (lambda m: m["env"].update(max_ops=10**7), r"env.max_ops must be an integer in \[1, 1000\]"),
    (lambda m: m["extra"].update(env_settings={"max_ops": 10**7}), r"max_ops must be an integer in \[1, 1000\]"),
    (lambda m: m.update(extra={"env_kwargs": {"max_ops": 1e7}}), r"env_kwargs.*max_ops"),
    (lambda m: m["extra"].update(env_settings={"failed_pick_cost": 1e9}), r"failed_pick_cost .* \[0, 3600\]"),
])
def test_crafted_policy_metadata_is_refused_naming_the_file(tmp_path, change, match):
    path = _policy(tmp_path, hidden=8)
    _rewrite_meta(path, change)
    rss = _maxrss_kb()
    t0 = time.perf_counter()
    with pytest.raises(PolicyError, match=match) as exc:
        load_agent(path, SPEC)
    assert str(path) in str(exc.value)
    assert time.perf_counter() - t0 < 1.0 and _maxrss_kb() - rss < 50 * 1024  # refused before allocating


def test_deep_and_large_json_policies_are_policy_errors(tmp_path):
    deep = tmp_path / "deep.json"
    deep.write_bytes(b"{\"x\": " + b"[" * 100_000 + b"]" * 100_000 + b"}")
    with pytest.raises(PolicyError, match=r"deep\.json.*nested 100001 levels deep"):
        load_agent(deep, SPEC)
    meta = json.dumps({"format": "perception_config.policy", "agent": "random", "env": SPEC.to_json(),
                       "state": {"x": "[" * 1000}})  # brackets inside strings do not count
    ok = tmp_path / "ok.json"
    ok.write_text(meta)
    assert load_agent(ok, SPEC).kind == "random"  # no checksum (an older file): accepted with the other checks
    with pytest.raises(PolicyError, match=r"is a directory"):
        load_agent(tmp_path, SPEC)


def test_weights_must_be_finite_and_match_the_checksum(tmp_path):
    path = _policy(tmp_path, hidden=8)
    assert load_agent(path, SPEC).hidden == 8
    data = bytearray(path.read_bytes())
    data[-5] ^= 0x20  # one bit of the last weight
    flipped = tmp_path / "flipped.policy"
    flipped.write_bytes(bytes(data))
    with pytest.raises(PolicyError, match=r"flipped\.policy is corrupt: its content does not match its sha256"):
        load_agent(flipped, SPEC)
    meta, tensors = read_file(path)
    tensors["policy.fc2.bias"][1] = np.nan
    meta.pop(CHECKSUM_KEY)
    write_file(path, meta, tensors)  # a consistent checksum, NaN weights
    with pytest.raises(PolicyError, match=r"tensor 'policy.fc2.bias' holds NaN"):
        load_agent(path, SPEC)


def test_tensor_shapes_are_checked_against_the_hparams_before_building(tmp_path):
    path = _policy(tmp_path, hidden=8)
    _rewrite_meta(path, lambda m: m["hparams"].update(hidden=4000))  # within bounds, but not the file's tensors
    with pytest.raises(PolicyError, match=r"are not the .* that its 'pg' hyper-parameters and the environment imply"):
        load_agent(path, SPEC)
    es = _policy(tmp_path, "es", population=4, hidden=[5, 6])
    assert load_agent(es, SPEC).hidden == [5, 6]
    _rewrite_meta(es, lambda m: m["hparams"].update(hidden=[5, 7]))
    with pytest.raises(PolicyError, match=r"es\.policy is corrupt: its tensors"):
        load_agent(es, SPEC)


def test_policy_without_checksum_is_still_accepted(tmp_path):
    """Files written before the checksum existed load, with every other check."""
    path = _policy(tmp_path, hidden=8)
    _rewrite_meta(path, lambda m: None, checksum=False)
    meta, _ = read_file(path)
    assert CHECKSUM_KEY not in meta
    assert load_agent(path, SPEC).hidden == 8


# --------------------------------------------------------------------------- policy files: fuzz


def _mutate_bytes(rng: np.random.Generator, data: bytes) -> bytes:
    b = bytearray(data)
    op = rng.integers(4)
    if op == 0:  # bit flips
        for _ in range(int(rng.integers(1, 8))):
            i = int(rng.integers(len(b)))
            b[i] ^= 1 << int(rng.integers(8))
    elif op == 1:  # truncation
        b = b[:int(rng.integers(len(b)))]
    elif op == 2:  # swap two ranges
        i, j = sorted(int(x) for x in rng.integers(len(b), size=2))
        n = int(rng.integers(1, 64))
        b[i:i + n], b[j:j + n] = b[j:j + n], b[i:i + n]
    else:  # overwrite with a number or a bracket run
        i = int(rng.integers(len(b)))
        b[i:i] = rng.choice([b"9" * 20, b"[" * 5000, b"-1", b"1e309", b"\x00\xff", b'"'])
    return bytes(b)


_HOSTILE_VALUES = [None, -1, 0, 10**12, 3e6, 1e309, float("nan"), "x", "", [], {}, [1, 2], {"a": 1}, True,
                   [[[[[[[[[[]]]]]]]]]], 2**70, -0.5, "9" * 500]


def _mutate_json(rng: np.random.Generator, node, depth: int = 0):
    """A copy of a JSON value with one random field replaced, removed or added."""
    if isinstance(node, dict) and node and depth < 6 and rng.random() < 0.7:
        key = list(node)[int(rng.integers(len(node)))]
        out = dict(node)
        r = rng.random()
        if r < 0.1:
            del out[key]
        elif r < 0.2:
            out["fuzz" + str(int(rng.integers(100)))] = _HOSTILE_VALUES[int(rng.integers(len(_HOSTILE_VALUES)))]
        else:
            out[key] = _mutate_json(rng, node[key], depth + 1)
        return out
    if isinstance(node, list) and node and depth < 6 and rng.random() < 0.7:
        out = list(node)
        i = int(rng.integers(len(out)))
        out[i] = _mutate_json(rng, out[i], depth + 1)
        return out
    return _HOSTILE_VALUES[int(rng.integers(len(_HOSTILE_VALUES)))]


def _attempt_seconds(attempt, item, allowed: tuple[type[BaseException], ...]) -> tuple[float, bool]:
    """Wall-clock seconds of one attempt and whether it loaded; any exception outside `allowed` propagates."""
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            attempt(item)
            loaded = True
        except allowed:
            loaded = False
    return time.perf_counter() - t0, loaded


def _fuzz(inputs, attempt, allowed: tuple[type[BaseException], ...]) -> dict[str, int]:
    """Run `attempt` on each input until FUZZ_SECONDS; every outcome must be success or `allowed`.

    An input over MAX_INPUT_SECONDS is timed once more before it fails the test: on a shared CI machine one
    attempt in thousands can be stalled by the machine (2.2 s once, for an input that takes milliseconds),
    while an input that is slow by itself is slow both times."""
    counts = {"tried": 0, "loaded": 0, "refused": 0}
    rss0 = _maxrss_kb()
    t_end = time.perf_counter() + FUZZ_SECONDS
    for item in inputs:
        if time.perf_counter() > t_end:
            break
        seconds, loaded = _attempt_seconds(attempt, item, allowed)
        counts["loaded" if loaded else "refused"] += 1
        counts["tried"] += 1
        if seconds >= MAX_INPUT_SECONDS:
            seconds = min(seconds, _attempt_seconds(attempt, item, allowed)[0])
        assert seconds < MAX_INPUT_SECONDS, f"input #{counts['tried']} took {seconds:.2f} s twice"
    assert _maxrss_kb() - rss0 < MAX_RSS_GROWTH_KB
    print(f"fuzz: {counts}")
    return counts


@pytest.mark.parametrize("kind", ["pg", "es", "simple"])
def test_fuzz_policy_loader(tmp_path, kind):
    kw = {"pg": {"hidden": 8}, "es": {"population": 4, "hidden": [4, 4]}, "simple": {}}[kind]
    agent = make_agent(kind, SPEC, **kw)
    if kind == "simple":
        agent.set_state({"episodes": 3, "memory": [{"key": [0], "q": [-1.0, -2.0, -3.0], "n": [1, 1, 1]}]})
    good = save_agent(agent, tmp_path / f"good.{kind}", {"env_settings": {"max_ops": 6}})
    data = good.read_bytes()
    meta, tensors = read_file(good)
    rng = np.random.default_rng(14)
    target = tmp_path / "fuzzed"

    def inputs():
        while True:
            if rng.random() < 0.5:
                yield _mutate_bytes(rng, data)
            else:  # a structurally valid file (fresh checksum) with a hostile field
                m = _mutate_json(rng, meta)
                if isinstance(m, dict):
                    m.pop(CHECKSUM_KEY, None)
                try:
                    write_file(target, m, tensors) if isinstance(m, dict) else None
                except (TypeError, ValueError, OverflowError):
                    continue  # not even writable as JSON
                yield target.read_bytes() if isinstance(m, dict) else json.dumps(m).encode()

    def attempt(blob: bytes) -> None:
        target.write_bytes(blob)
        load_agent(target, SPEC)

    counts = _fuzz(inputs(), attempt, (PolicyError,))
    assert counts["tried"] >= 100 and counts["refused"] > 0


# --------------------------------------------------------------------------- datasets


def _png_header_claiming(path: Path, w: int, h: int) -> None:
    """A small PNG whose IHDR declares w x h (the data is a few bytes): decoding it would allocate w*h*3."""
    ihdr = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)
    chunk = lambda t, d: struct.pack(">I", len(d)) + t + d + struct.pack(">I", zlib.crc32(t + d))  # noqa: E731
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 1000))
                     + chunk(b"IEND", b""))


def test_crafted_bop_files_are_bop_errors(tmp_path):
    root = make_tiny_dataset(tmp_path / "tiny")
    scene = root / "test" / "000001"
    gt = scene / "scene_gt.json"
    gt.write_bytes(b"[" * 200_000 + b"]" * 200_000)
    with pytest.raises(BopFormatError, match=r"scene_gt\.json: JSON nested 200000 levels deep"):
        BopDataset(root).load_frame(1, 0)

    root = make_tiny_dataset(tmp_path / "tiny2")
    rgb = root / "test" / "000001" / "rgb" / "000002.png"
    rgb.unlink()
    rgb.mkdir()
    with pytest.raises(BopFormatError, match=r"rgb/000002\.png: is a directory"):
        BopDataset(root).load_frame(1, 2)
    rgb.rmdir()
    _png_header_claiming(rgb, 20000, 20000)
    rss, t0 = _maxrss_kb(), time.perf_counter()
    with pytest.raises(BopFormatError, match=r"000002\.png: PNG image of 20000 x 20000 pixels is over the limit"):
        BopDataset(root).load_frame(1, 2)
    assert time.perf_counter() - t0 < 0.5 and _maxrss_kb() - rss < 50 * 1024  # refused from the header
    assert 20000 * 20000 > MAX_IMAGE_PIXELS


def test_safe_json_ignores_brackets_in_strings_and_limits_size():
    assert loads_limited(b'{"a": "[[[[\\"]]"}', "x", max_depth=1) == {"a": '[[[["]]'}
    with pytest.raises(ValueError, match=r"x: 12 bytes of JSON, more than the 10-byte limit"):
        loads_limited(b'"0123456789"', "x", max_bytes=10)


def test_fuzz_bop_reader(tmp_path):
    root = make_tiny_dataset(tmp_path / "tiny", scenes=1, images=2)
    scene = root / "test" / "000001"
    files = {p: p.read_bytes() for p in [scene / "scene_gt.json", scene / "scene_camera.json",
                                         scene / "scene_gt_info.json", scene / "rgb" / "000000.png",
                                         scene / "depth" / "000000.png"]}
    rng = np.random.default_rng(4)

    def inputs():
        while True:
            path = list(files)[int(rng.integers(len(files)))]
            data = files[path]
            if path.suffix == ".json" and rng.random() < 0.5:
                blob = json.dumps(_mutate_json(rng, json.loads(data))).encode()
            elif path.suffix == ".png" and rng.random() < 0.3:  # another declared size in IHDR
                w, h = (int(x) for x in rng.choice([0, 1, 64, 30000, 2**31 - 1, 2**32 - 1], size=2))
                blob = data[:16] + struct.pack(">II", w, h) + data[24:]
            else:
                blob = _mutate_bytes(rng, data)
            yield path, blob

    def attempt(item) -> None:
        path, blob = item
        for p, d in files.items():
            p.write_bytes(blob if p == path else d)
        BopDataset(root).load_frame(1, 0)

    counts = _fuzz(inputs(), attempt, (BopFormatError,))
    assert counts["tried"] >= 50 and counts["refused"] > 0


# --------------------------------------------------------------------------- bags


@pytest.fixture(scope="module")
def bag_file(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("hostile_bag")
    write_frames([make_frame(i, h=12, w=16) for i in range(4)], d / "bag")
    return d / "bag" / "bag_0.mcap"


def test_corrupt_chunk_is_reported_by_bag_info(bag_file, tmp_path):
    from mcap.records import Chunk
    from mcap.stream_reader import StreamReader

    with open(bag_file, "rb") as f:
        reader = StreamReader(f, emit_chunks=True)
        ends = [f.tell() for rec in reader.records if isinstance(rec, Chunk)]
    assert bag_info(bag_file)["corrupt"] is False
    data = bytearray(bag_file.read_bytes())
    data[ends[1] - 40] ^= 0x10  # inside the second chunk's records
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    info = bag_info(bad)
    assert info["corrupt"] and info["truncated"] and "bad.mcap" in info["damage"]
    assert info["frames"] < 4  # only what precedes the damage
    with pytest.raises(BagFormatError, match=r"bad\.mcap: damaged MCAP data"):
        list(read_bag(bad))


@pytest.mark.parametrize("name", ["this/msg/Zen", "os/msg/path", "sensor_msgs/msg/../Image", "a.b/msg/C",
                                  "sensor_msgs/msg/Image;x", "/msg/Image", "sensor_msgs/srv/Foo/Bar"])
def test_bag_type_names_are_validated_before_any_import(name):
    with pytest.raises(BagFormatError, match=r"message type"):
        check_type_name(name)


def test_replay_does_not_import_a_module_named_by_the_bag():
    bag_replay_node = pytest.importorskip("perception_config.ros.bag_replay_node")
    sys.modules.pop("this", None)
    with pytest.raises(BagFormatError, match=r"'this' is not a known ROS interface package"):
        bag_replay_node.message_class("this/msg/Zen")
    assert "this" not in sys.modules
    assert bag_replay_node.message_class("sensor_msgs/msg/Image").__name__ == "Image"


def test_fuzz_bag_reader(bag_file, tmp_path):
    data = bag_file.read_bytes()
    rng = np.random.default_rng(7)
    target = tmp_path / "fuzzed.mcap"

    def attempt(blob: bytes) -> None:
        target.write_bytes(blob)
        bag_info(target)
        list(read_bag(target))

    counts = _fuzz((_mutate_bytes(rng, data) for _ in iter(int, 1)), attempt, (BagFormatError,))
    assert counts["tried"] >= 30 and counts["refused"] > 0


def test_model_and_results_files_refuse_directories(tmp_path):
    from perception_config.core.ply import PlyError, read_ply
    from perception_config.datasets.bop_results import read_results_csv

    (tmp_path / "obj.ply").mkdir()
    with pytest.raises(PlyError, match=r"obj\.ply: is a directory, not a PLY file"):
        read_ply(tmp_path / "obj.ply")
    (tmp_path / "res.csv").mkdir()
    with pytest.raises(BopFormatError, match=r"res\.csv: is a directory"):
        read_results_csv(tmp_path / "res.csv")


def test_chunk_declaring_a_huge_size_is_damage_not_decompressed(bag_file, tmp_path):
    from mcap.reader import SeekingReader

    with open(bag_file, "rb") as f:
        start = SeekingReader(f).get_summary().chunk_indexes[1].chunk_start_offset
    data = bytearray(bag_file.read_bytes())
    data[start + 1 + 8 + 16:start + 1 + 8 + 24] = struct.pack("<Q", 2**40)  # uncompressed_size: 1 TiB
    bomb = tmp_path / "bomb.mcap"
    bomb.write_bytes(bytes(data))
    rss = _maxrss_kb()
    info = bag_info(bomb)
    assert info["corrupt"] and "declares 1099511627776 uncompressed bytes" in info["damage"]
    try:  # read_bag trusts the zstd frame's own content size: it loads (the data is intact) or refuses
        list(read_bag(bomb))
    except BagFormatError as exc:
        assert "bomb.mcap" in str(exc)
    assert _maxrss_kb() - rss < 100 * 1024
