"""A node parameter written down once (NodeParameter): the node declares it with the full
rcl_interfaces descriptor built from it, so `ros2 param describe <node> <name>` tells its
description, type, range, choices and whether it may change at run time, and the generated
reference (parameter_docs.py) reads the same spec.

A range is given only where no value outside it ever worked (the node refused it at start-up
or at each use, or, for a setting of a mode that is off, never read it): rclpy now refuses such
a value itself, when the node starts (the node exits 2 naming it) or when it is set.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, ParameterType
from rclpy.node import Node
from rclpy.parameter import Parameter

INT_MAX = 2**63 - 1  # an integer range with no upper limit ends here (ParameterDescriptor's int64)

TYPE_NAMES = {  # as `ros2 param describe` names them
    ParameterType.PARAMETER_BOOL: "boolean",
    ParameterType.PARAMETER_INTEGER: "integer",
    ParameterType.PARAMETER_DOUBLE: "double",
    ParameterType.PARAMETER_STRING: "string",
    ParameterType.PARAMETER_STRING_ARRAY: "string array",
}


@dataclass(frozen=True)
class NodeParameter:
    """One parameter of a node. `default` is the value, or a Parameter.Type for a parameter that
    is not set unless given. `limits` are inclusive bounds (a range). `read_only`: the node reads
    it only at start-up. `choices`: the strings it accepts. `number`: an integer or a double
    (rate:=0 and rate:=0.5 both work)."""

    name: str
    default: Any
    description: str
    limits: tuple[float, float] | None = None
    read_only: bool = False
    choices: tuple[str, ...] = ()
    number: bool = False

    @property
    def type(self) -> int:
        if isinstance(self.default, Parameter.Type):
            return self.default.value
        return Parameter.Type.from_parameter_value(self.default).value

    def type_name(self) -> str:
        name = TYPE_NAMES[self.type]
        return f"{name} or integer" if self.number else name

    def range_text(self) -> str:
        """The range as "[low, high]" ("inf": no upper limit), or ""."""
        if self.limits is None:
            return ""
        low, high = self.limits
        return f"[{low!r}, {'inf' if high == INT_MAX else repr(high)}]"

    def descriptor(self) -> ParameterDescriptor:
        descriptor = ParameterDescriptor(name=self.name, type=self.type, description=self.description,
                                         read_only=self.read_only, dynamic_typing=self.number)
        if self.choices:
            descriptor.additional_constraints = "one of: " + ", ".join(self.choices)
        if self.limits is not None:
            low, high = self.limits
            if self.type == ParameterType.PARAMETER_INTEGER:
                descriptor.integer_range = [IntegerRange(from_value=low, to_value=high, step=0)]
            else:
                descriptor.floating_point_range = [FloatingPointRange(from_value=float(low), to_value=float(high),
                                                                      step=0.0)]
        return descriptor

    def row(self) -> dict[str, Any]:
        """This parameter as a row of the reference table (parameter_docs.py)."""
        default = None if isinstance(self.default, Parameter.Type) else self.default
        default = list(default) if isinstance(default, list) else default  # the spec's own list stays as it is
        return {"name": self.name, "type": self.type_name(), "default": default, "description": self.description,
                "range": self.range_text(), "read_only": self.read_only}


def declare(node: Node, parameters: tuple[NodeParameter, ...]) -> None:
    """Declare `parameters` on `node`, in order, each with its descriptor."""
    node.declare_parameters("", [(p.name, p.default, p.descriptor()) for p in parameters])
