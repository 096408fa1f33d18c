"""estimate_pose as a robot program calls it: one request per object in a frame named by stamp,
waiting for the answer. replay-check and cell-sim both drive the running configurator with it."""
from __future__ import annotations

import time
from typing import Any

import rclpy
from perception_config_interfaces.srv import EstimatePose
from rclpy.node import Node


class EstimateClient:
    """An EstimatePose client on `node`; `call` spins the node (its subscriptions run too)
    until the answer arrives."""

    def __init__(self, node: Node, service: str = "estimate_pose", timeout: float = 120.0,
                 wait: float = 60.0) -> None:
        self.node = node
        self.timeout = timeout
        self.client = node.create_client(EstimatePose, service)
        if not self.client.wait_for_service(timeout_sec=wait):
            raise RuntimeError(f"{service} did not appear within {wait:g} s: see the configurator's log")
        self._warm_up(service, wait)

    def _warm_up(self, service: str, wait: float) -> None:
        """Seeing the service does not mean the service sees this client's answer reader yet: an
        answer sent before that is lost (rmw_fastrtps). An empty request, refused at once, is
        repeated until one answer comes back; then the estimates' answers arrive."""
        deadline = time.monotonic() + wait
        while time.monotonic() < deadline:
            future = self.client.call_async(EstimatePose.Request())
            rclpy.spin_until_future_complete(self.node, future, timeout_sec=1.0)
            if future.done():
                return
        raise RuntimeError(f"{service} answered none of its first requests within {wait:g} s")

    def call(self, stamp_ns: int, obj_id: int | str, noise_lambda: float, seed: int) -> dict[str, Any]:
        """One estimate: the answer's fields as plain Python plus `wall` (seconds from request to
        answer) and `estimate_id` (the configurator's episode store id; 0 when it has none)."""
        req = EstimatePose.Request(object_id=str(obj_id), noise_lambda=float(noise_lambda), seed=int(seed))
        req.frame.stamp.sec, req.frame.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
        t0 = time.perf_counter()
        future = self.client.call_async(req)
        rclpy.spin_until_future_complete(self.node, future, timeout_sec=self.timeout)
        wall = time.perf_counter() - t0
        res = future.result()
        if res is None:
            raise RuntimeError(f"estimate_pose gave no answer within {self.timeout:g} s")
        return {"success": bool(res.success), "message": res.message, "picked": bool(res.picked),
                "operations": list(res.operations), "operation_seconds": list(res.operation_elapsed),
                "wall": wall, "estimate_id": int(getattr(res, "estimate_id", 0) or 0)}

    def close(self) -> None:
        self.node.destroy_client(self.client)
