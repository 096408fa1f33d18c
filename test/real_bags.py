"""Camera recordings as real ROS 2 systems write them, for tests: written by `rosbags` (its rosbag2
Writer: MCAP or sqlite3 storage, chunk or message zstd compression) or, for lz4 MCAP chunks (which
rosbags does not write), by the `mcap` library with rosbags' CDR and definitions; never by the
project's own writer. Images raw (sensor_msgs/Image) or as image_transport CompressedImage (jpeg,
png, compressedDepth), topics laid out as a camera driver publishes them."""
from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from perception_config.core.scene import Frame

NS0 = 1_720_000_000 * 10**9 + 123_456
PERIOD_NS = 33_333_333
K = np.array([[30.0, 0, 16.5], [0, 31.0, 12.25], [0, 0, 1]])
# driver -> (namespace, colour, depth, camera_info, a distractor image topic)
LAYOUTS = {
    "realsense": ("/camera/camera/", "color/image_raw", "aligned_depth_to_color/image_raw", "color/camera_info",
                  "depth/image_rect_raw"),
    "realsense_old": ("/camera/", "color/image_raw", "aligned_depth_to_color/image_raw", "color/camera_info",
                      "infra1/image_rect_raw"),
    "azure_kinect": ("/", "rgb/image_raw", "depth_to_rgb/image_raw", "rgb/camera_info", "depth/image_raw"),
    "zed": ("/zed/zed_node/", "rgb/image_rect_color", "depth/depth_registered", "rgb/camera_info",
            "left_raw/image_raw_color"),
    "oak": ("/oak/", "rgb/image_raw", "stereo/image_raw", "rgb/camera_info", "left/image_rect"),
}
QUANT_A, MAX_DEPTH = 100.0, 10.0  # compressed_depth_image_transport's defaults (depth_quantization, depth_max)


@dataclass
class Spec:
    storage: str = "mcap"  # mcap | sqlite3
    compression: str = "none"  # none | chunk-zstd | chunk-lz4 | message-zstd | message-lz4
    type_form: str = "msg"  # msg: sensor_msgs/msg/Image; short: sensor_msgs/Image
    layout: str = "realsense"
    color: str = "rgb8"  # rgb8 | bgr8 | jpeg | png
    depth: str = "16UC1"  # 16UC1 | 32FC1 | compressedDepth-16UC1 | compressedDepth-32FC1 | png
    n: int = 3
    h: int = 24
    w: int = 32

    def topics(self) -> dict[str, str]:
        """role -> topic name as written."""
        ns, c, d, i, x = LAYOUTS[self.layout]
        color = ns + c + ("/compressed" if self.color in ("jpeg", "png") else "")
        depth = ns + d + ("/compressedDepth" if self.depth.startswith("compressedDepth") else
                          "/compressed" if self.depth == "png" else "")
        return {"color": color, "depth": depth, "camera_info": ns + i, "distractor": ns + x}


def compressed_depth(depth_m: np.ndarray, source: str) -> bytes:
    """compressed_depth_image_transport's format: int32 format, float32 quantA, quantB, then a PNG of
    16UC1 millimetres or of the 32FC1 inverse depth quantised as A / depth + B (0 = missing)."""
    if source == "16UC1":
        mm = np.where(np.isfinite(depth_m), np.rint(depth_m * 1000), 0).astype(np.uint16)
        header, img = struct.pack("<iff", 1, 0.0, 0.0), mm
    else:
        quant_b = 1.0 - QUANT_A / MAX_DEPTH
        with np.errstate(divide="ignore", invalid="ignore"):
            q = QUANT_A / depth_m + quant_b
        img = np.where(np.isfinite(depth_m), q, 0).astype(np.uint16)  # the C++ cast truncates
        header = struct.pack("<iff", 0, QUANT_A, quant_b)
    ok, png = cv2.imencode(".png", img)
    assert ok
    return header + png.tobytes()


def write_camera_bag(path: Path, spec: Spec) -> list[Frame]:
    """Write the bag; the frames a reader must recover (depth in metres, NaN = missing)."""
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    Header, Time = T["std_msgs/msg/Header"], T["builtin_interfaces/msg/Time"]
    rng = np.random.default_rng(3)
    topics = spec.topics()
    h, w = spec.h, spec.w

    def header(ns: int, frame: str):
        return Header(stamp=Time(sec=ns // 10**9, nanosec=ns % 10**9), frame_id=frame)

    def image(ns: int, enc: str, arr: np.ndarray, frame: str):
        arr = np.ascontiguousarray(arr)
        return T["sensor_msgs/msg/Image"](header=header(ns, frame), height=arr.shape[0], width=arr.shape[1],
                                          encoding=enc, is_bigendian=0, step=arr.strides[0],
                                          data=np.frombuffer(arr.tobytes(), np.uint8))

    def compressed(ns: int, fmt: str, data: bytes, frame: str):
        return T["sensor_msgs/msg/CompressedImage"](header=header(ns, frame), format=fmt,
                                                    data=np.frombuffer(data, np.uint8))

    def info(ns: int):
        return T["sensor_msgs/msg/CameraInfo"](
            header=header(ns, "cam"), height=h, width=w, distortion_model="plumb_bob", d=np.zeros(5),
            k=K.flatten(), r=np.eye(3).flatten(), p=np.hstack([K, np.zeros((3, 1))]).flatten(), binning_x=0,
            binning_y=0, roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                                    do_rectify=False))

    records: list[tuple[str, str, int, bytes]] = []  # topic, type, log time, cdr
    expect = []
    for k in range(spec.n):
        t = NS0 + k * PERIOD_NS
        yy, xx = np.mgrid[0:h, 0:w]
        rgb = np.stack([(xx * 7 + k * 10) % 256, (yy * 9) % 256, (xx + yy) * 3 % 256], axis=2).astype(np.uint8)
        mm = rng.integers(200, 1500, (h, w)).astype(np.uint16)
        mm[rng.random((h, w)) < 0.2] = 0
        depth = mm.astype(np.float32) / np.float32(1000)
        depth[mm == 0] = np.nan
        if spec.color in ("jpeg", "png"):
            ok, buf = cv2.imencode("." + ("jpg" if spec.color == "jpeg" else "png"), rgb[:, :, ::-1])
            col = compressed(t, f"rgb8; {spec.color} compressed bgr8", buf.tobytes(), "cam")
            col_type = "sensor_msgs/msg/CompressedImage"
            if spec.color == "jpeg":
                rgb = cv2.imdecode(buf, cv2.IMREAD_COLOR)[:, :, ::-1]  # what any jpeg decoder gives
        else:
            col = image(t, spec.color, rgb[:, :, ::-1] if spec.color == "bgr8" else rgb, "cam")
            col_type = "sensor_msgs/msg/Image"
        if spec.depth.startswith("compressedDepth"):
            source = spec.depth.split("-")[1]
            dep = compressed(t, f"{source}; compressedDepth png", compressed_depth(depth, source), "cam")
            dep_type = "sensor_msgs/msg/CompressedImage"
            if source == "32FC1":  # what the quantisation keeps
                q = np.where(np.isfinite(depth), QUANT_A / depth + (1 - QUANT_A / MAX_DEPTH), 0).astype(np.uint16)
                with np.errstate(divide="ignore"):
                    depth = (np.float32(QUANT_A) / (q.astype(np.float32) - np.float32(1 - QUANT_A / MAX_DEPTH)))
                depth[q == 0] = np.nan
        elif spec.depth == "png":
            ok, buf = cv2.imencode(".png", mm)
            dep = compressed(t, "16UC1; png compressed mono16", buf.tobytes(), "cam")
            dep_type = "sensor_msgs/msg/CompressedImage"
        elif spec.depth == "32FC1":
            dep, dep_type = image(t, "32FC1", depth.astype("<f4"), "cam"), "sensor_msgs/msg/Image"
        else:
            dep, dep_type = image(t, "16UC1", mm, "cam"), "sensor_msgs/msg/Image"
        records += [
            (topics["distractor"], "sensor_msgs/msg/Image", t + 1_000_000,
             ts.serialize_cdr(image(t, "mono8", rgb[:-2, :, 0], "other"), "sensor_msgs/msg/Image")),
            (topics["depth"], dep_type, t + 2_000_000, ts.serialize_cdr(dep, dep_type)),
            (topics["color"], col_type, t + 3_000_000, ts.serialize_cdr(col, col_type)),
            (topics["camera_info"], "sensor_msgs/msg/CameraInfo", t + 3_000_000,
             ts.serialize_cdr(info(t), "sensor_msgs/msg/CameraInfo")),
        ]
        expect.append(Frame(rgb, depth, K, stamp=t / 1e9))
    _write(path, spec, ts, records)
    return expect


def type_name(spec: Spec, msgtype: str) -> str:
    return msgtype.replace("/msg/", "/") if spec.type_form == "short" else msgtype


def _write(path: Path, spec: Spec, ts, records: list[tuple[str, str, int, bytes]]) -> None:
    if spec.compression == "chunk-lz4":
        from mcap.writer import CompressionType, Writer

        path.mkdir()
        with open(path / f"{path.name}_0.mcap", "wb") as f:
            wr = Writer(f, compression=CompressionType.LZ4, chunk_size=4096)
            wr.start(profile="ros2", library="mcap test writer")
            chans = {}
            for topic, msgtype, log_time, data in records:
                if topic not in chans:
                    schema = wr.register_schema(type_name(spec, msgtype), "ros2msg",
                                                ts.generate_msgdef(msgtype, ros_version=2)[0].encode())
                    chans[topic] = wr.register_channel(topic, "cdr", schema)
                wr.add_message(chans[topic], log_time, data, log_time)
            wr.finish()
        return
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

    plugin = StoragePlugin.MCAP if spec.storage == "mcap" else StoragePlugin.SQLITE3
    wr = Writer(path, version=9, storage_plugin=plugin)
    if spec.compression == "chunk-zstd":
        wr.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    elif spec.compression == "message-zstd":
        wr.set_compression(CompressionMode.MESSAGE, CompressionFormat.ZSTD)
    with wr:
        conns = {}
        for topic, msgtype, log_time, data in records:
            if topic not in conns:
                conns[topic] = wr.add_connection(topic, type_name(spec, msgtype),
                                                 msgdef=ts.generate_msgdef(msgtype, ros_version=2)[0],
                                                 rihs01=ts.hash_rihs01(msgtype))
            if spec.compression == "message-lz4":  # lz4 frames per message (rosbag2's own compressor is zstd)
                import lz4.frame

                data = lz4.frame.compress(bytes(data))
            wr.write(conns[topic], log_time, data)
