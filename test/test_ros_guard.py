"""The last-resort guard (ros/guard.py) on a real rclpy node in this process: a service callback
that raises is answered success=false with the exception, a subscription or timer callback that
raises is logged and dropped, a parameter callback that raises refuses the change, and in every
case the node's executor keeps spinning."""
from __future__ import annotations

import threading
import time

import pytest

from ros_helpers import call, publish_when_matched

pytestmark = pytest.mark.ros


def test_a_raising_callback_is_answered_or_logged_and_the_node_keeps_spinning(ros_node):
    import rclpy
    from perception_config_interfaces.srv import ReportPickOutcome
    from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
    from rcl_interfaces.srv import SetParameters
    from rclpy.executors import SingleThreadedExecutor
    from std_msgs.msg import String

    from perception_config.ros.guard import GuardedNode

    calls = {"service": 0, "async": 0, "topic": 0, "timer": 0}

    class Fragile(GuardedNode):
        def __init__(self) -> None:
            super().__init__(f"fragile_{id(self)}")
            self.declare_parameter("knob", 1)
            self.create_service(ReportPickOutcome, "~/plain", self._plain)
            self.create_service(ReportPickOutcome, "~/async", self._async)
            self.create_subscription(String, "~/topic", self._topic, 10)
            self.create_timer(0.05, self._timer)
            self.add_on_set_parameters_callback(self._params)

        def _plain(self, request, response):
            calls["service"] += 1
            if request.picked:
                raise OverflowError("Python int too large to convert to SQLite INTEGER")
            response.success, response.message = True, "fine"
            return response

        async def _async(self, request, response):
            calls["async"] += 1
            raise KeyError("boom")

        def _topic(self, msg):
            calls["topic"] += 1
            raise RuntimeError(f"bad message {msg.data}")

        def _timer(self):
            calls["timer"] += 1
            raise ZeroDivisionError("tick")

        def _params(self, params):
            raise TypeError("bad parameter callback")

    node = Fragile()
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    stop = threading.Event()
    errors: list[BaseException] = []

    def spin():
        try:
            while not stop.is_set():
                executor.spin_once(timeout_sec=0.05)
        except BaseException as exc:  # what the guard must prevent
            errors.append(exc)

    thread = threading.Thread(target=spin, daemon=True)
    thread.start()
    try:
        name = node.get_fully_qualified_name()
        plain = ros_node.create_client(ReportPickOutcome, f"{name}/plain")
        anc = ros_node.create_client(ReportPickOutcome, f"{name}/async")
        params = ros_node.create_client(SetParameters, f"{name}/set_parameters")
        for c in (plain, anc, params):
            assert c.wait_for_service(timeout_sec=10.0)
        res = call(ros_node, plain, ReportPickOutcome.Request(picked=True))
        assert not res.success and res.message.startswith("internal error: OverflowError"), res.message
        res = call(ros_node, anc, ReportPickOutcome.Request())
        assert not res.success and "KeyError('boom')" in res.message, res.message
        pub = ros_node.create_publisher(String, f"{name}/topic", 10)
        publish_when_matched(ros_node, pub, String(data="x"))
        deadline = time.monotonic() + 5.0
        while (calls["topic"] < 1 or calls["timer"] < 3) and time.monotonic() < deadline:
            rclpy.spin_once(ros_node, timeout_sec=0.05)
        assert calls["topic"] >= 1 and calls["timer"] >= 3, calls
        req = SetParameters.Request(parameters=[Parameter(name="knob", value=ParameterValue(
            type=ParameterType.PARAMETER_INTEGER, integer_value=2))])
        result = call(ros_node, params, req).results[0]
        assert not result.successful and "internal error: TypeError" in result.reason, result.reason
        # still serving after all that
        assert call(ros_node, plain, ReportPickOutcome.Request(picked=False)).message == "fine"
        assert thread.is_alive() and not errors, errors
        ros_node.destroy_publisher(pub)
        for c in (plain, anc, params):
            ros_node.destroy_client(c)
    finally:
        stop.set()
        thread.join(5.0)
        executor.shutdown()
        node.destroy_node()
