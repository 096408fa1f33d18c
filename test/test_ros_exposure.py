"""What a node exposes with the project's defaults, and what it leaves in /dev/shm."""
from __future__ import annotations

import ipaddress
import os
import signal
import socket
import struct
import time
from pathlib import Path

import pytest

from perception_config.launcher.fastdds_shm import clean_stale_fastdds_shm
from ros_helpers import NodeProcess, wait_for_service

pytestmark = pytest.mark.ros

SHM = Path("/dev/shm")
NAMESPACE = "/exposure_test"


def _socket_inodes(pid: int) -> set[int]:
    inodes = set()
    for fd in os.listdir(f"/proc/{pid}/fd"):
        try:
            target = os.readlink(f"/proc/{pid}/fd/{fd}")
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(int(target[len("socket:["):-1]))
    return inodes


def _address(hex_addr: str, v6: bool) -> str:
    ip, port = hex_addr.split(":")
    raw = bytes.fromhex(ip)
    if v6:  # four host-order 32-bit words
        raw = b"".join(struct.pack("<I", struct.unpack(">I", raw[i:i + 4])[0]) for i in range(0, 16, 4))
        return f"[{socket.inet_ntop(socket.AF_INET6, raw)}]:{int(port, 16)}"
    return f"{socket.inet_ntoa(struct.pack('<I', int(ip, 16)))}:{int(port, 16)}"


def node_sockets(pid: int) -> list[tuple[str, str]]:
    """(protocol, local address:port) of every UDP/TCP socket the process holds (/proc, like ss -uapn)."""
    inodes, found = _socket_inodes(pid), []
    for proto in ("udp", "udp6", "tcp", "tcp6"):
        lines = Path(f"/proc/{pid}/net/{proto}").read_text().splitlines()[1:]
        for fields in (line.split() for line in lines):
            if int(fields[9]) in inodes:
                found.append((proto, _address(fields[1], proto.endswith("6"))))
    return found


def _is_loopback(address: str) -> bool:
    return ipaddress.ip_address(address.rsplit(":", 1)[0].strip("[]")).is_loopback


def _segments_of(pid: int) -> set[str]:
    """The Fast DDS segments whose lock file the process holds open."""
    names = set()
    for fd in os.listdir(f"/proc/{pid}/fd"):
        try:
            target = os.readlink(f"/proc/{pid}/fd/{fd}")
        except OSError:
            continue
        if target.startswith(str(SHM / "fastdds_")) and target.endswith("_el") and "port" not in target:
            names.add(Path(target).name[:-3])
    return names


def _serving_generation_node(ros_node, models: Path) -> NodeProcess:
    from perception_config_interfaces.srv import GenerateHypothesis

    # A namespace of its own: a SIGKILLed node's service stays announced for the lease duration
    # (about 20 s), and a later test's client must not take it for its own node's.
    node = NodeProcess("generation_node", {"models_dir": str(models)}, remap={"__ns": NAMESPACE})
    deadline = time.monotonic() + 60
    # Its own log line, not the service: the service of the node killed before is still announced.
    while "serving generate_hypothesis" not in node.output():
        assert node.alive() and time.monotonic() < deadline, node.output()
        time.sleep(0.05)
    client = ros_node.create_client(GenerateHypothesis, f"{NAMESPACE}/generate_hypothesis")
    try:
        wait_for_service(ros_node, client, timeout=60, process=node)  # also: the two processes discover each other
    finally:
        ros_node.destroy_client(client)
    return node


@pytest.fixture(scope="module")
def models(tmp_path_factory) -> Path:
    from perception_config.datasets.parts import write_models

    return write_models(tmp_path_factory.mktemp("parts") / "models")


def test_a_node_binds_nothing_outside_loopback(ros_node, models):
    node = _serving_generation_node(ros_node, models)
    try:
        sockets = node_sockets(node.proc.pid)
    finally:
        node.stop()
    assert any(proto == "udp" for proto, _ in sockets), sockets  # the measurement sees the node's sockets
    assert [s for s in sockets if not _is_loopback(s[1])] == [], sockets
    assert all(proto == "udp" for proto, _ in sockets), sockets  # no TCP listener either


def test_a_killed_nodes_segment_is_removed_by_the_next_node_and_a_clean_stop_leaves_none(ros_node, models):
    first = _serving_generation_node(ros_node, models)
    killed = _segments_of(first.proc.pid)
    assert killed, "the node holds no Fast DDS segment lock"
    first.proc.send_signal(signal.SIGKILL)
    first.stop()
    assert all((SHM / name).exists() and (SHM / f"{name}_el").exists() for name in killed)  # Fast DDS leaves them
    time.sleep(max(0.0, 2.1 - min(time.time() - (SHM / f"{n}_el").stat().st_mtime for n in killed)))
    second = _serving_generation_node(ros_node, models)
    try:
        assert not any((SHM / name).exists() or (SHM / f"{name}_el").exists() for name in killed)
        own = _segments_of(second.proc.pid)
        assert own and not own & killed
        clean_stale_fastdds_shm(min_age_s=0.0)  # a live node's segment is never touched
        assert all((SHM / name).exists() for name in own)
    finally:
        assert second.stop() == 0
    assert not any((SHM / name).exists() or (SHM / f"{name}_el").exists() for name in own)  # a clean stop


def test_clean_keeps_held_and_young_segments_and_removes_stale_ones(tmp_path):
    import fcntl

    def segment(name: str, age_s: float) -> Path:
        (tmp_path / name).write_bytes(b"\0" * 64)
        lock = tmp_path / f"{name}_el"
        lock.touch()
        os.utime(lock, (time.time() - age_s, time.time() - age_s))
        return lock

    stale = segment("fastdds_00000000000000aa", 60)
    young = segment("fastdds_00000000000000bb", 0)
    held = segment("fastdds_00000000000000cc", 60)
    (tmp_path / "fastdds_port17910").touch()
    (tmp_path / "fastdds_port17910_el").touch()
    with open(held) as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        removed = clean_stale_fastdds_shm(tmp_path)
    assert sorted(removed) == ["fastdds_00000000000000aa", "fastdds_00000000000000aa_el"]
    assert not stale.exists() and young.exists() and held.exists() and (tmp_path / "fastdds_port17910").exists()
    assert clean_stale_fastdds_shm(tmp_path / "missing") == []
