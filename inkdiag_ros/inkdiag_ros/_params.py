"""Parameter declaration with descriptors (description, type, range), shared by the nodes."""

from __future__ import annotations

import contextlib

from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    ParameterType,
    SetParametersResult,
)

_TYPES = {
    bool: ParameterType.PARAMETER_BOOL,
    int: ParameterType.PARAMETER_INTEGER,
    float: ParameterType.PARAMETER_DOUBLE,
    str: ParameterType.PARAMETER_STRING,
    "int[]": ParameterType.PARAMETER_INTEGER_ARRAY,
    "str[]": ParameterType.PARAMETER_STRING_ARRAY,
}


def declare(node, name, default, description, *, kind=None, range_=None, read_only=False):
    """Declare ``name`` with a typed descriptor; ``range_=(lo, hi)`` for numbers (inclusive)."""
    kind = kind or type(default)
    d = ParameterDescriptor(name=name, type=_TYPES[kind], description=description,
                            read_only=read_only)
    if range_ is not None and kind is int:
        d.integer_range = [IntegerRange(from_value=int(range_[0]), to_value=int(range_[1]), step=1)]
    elif range_ is not None and kind is float:
        d.floating_point_range = [FloatingPointRange(from_value=float(range_[0]),
                                                     to_value=float(range_[1]), step=0.0)]
    node.declare_parameter(name, default, d)


def declare_all(node, params, dynamic=()) -> dict:
    """Declare every ``(name, default, description, kind, range)`` of ``params``; their values.

    Every parameter but those named in ``dynamic`` is read-only (its descriptor says so: ``ros2 param
    describe``; set at start with ``-p``, never after). An array parameter given as an empty list on the
    command line (``-p NAME:=[]``, which rclpy cannot type and leaves uninitialised) is the empty list.
    """
    from rclpy.exceptions import ParameterUninitializedException

    for name, default, desc, kind, rng in params:
        declare(node, name, default, desc, kind=kind, range_=rng, read_only=name not in dynamic)
    warn_unknown(node)
    out = {}
    for name, _, _, kind, _ in params:
        try:
            out[name] = node.get_parameter(name).value
        except ParameterUninitializedException:
            if kind not in ("int[]", "str[]"):
                raise
            out[name] = []
    return out


#: Names :func:`warn_unknown` leaves unsaid while :func:`shared_by` is in force.
_SHARED: frozenset = frozenset()


@contextlib.contextmanager
def shared_by(*tables):
    """Within: a node says nothing of a parameter it does not declare but one of ``tables`` (``PARAMS``
    of the other nodes a process builds) does: a graph's ``-p NAME:=VALUE`` reaches every node of it,
    meant for those that have NAME (``scripts/run --ros-args -p n_nozzles:=128``). A name no table
    declares is still warned about by each node."""
    global _SHARED
    before = _SHARED
    _SHARED = before | {row[0] for table in tables for row in table}
    try:
        yield
    finally:
        _SHARED = before


def warn_unknown(node) -> list:
    """Log the parameters given to ``node`` (``-p NAME:=VALUE``, a params file's section for it) that it
    does not declare, with the nearest declared name: rclpy ignores them, so a misspelt name
    (``max_queue_frames``) would leave its parameter at the default without a word. Returns their names
    (also ``node.ignored_parameters``). Call it after declaring every parameter."""
    import difflib

    given = getattr(node, "_parameter_overrides", {})  # rclpy's: this node's values from its arguments
    unknown = sorted(name for name in given if not node.has_parameter(name))
    node.ignored_parameters = unknown
    if said := [name for name in unknown if name not in _SHARED]:
        declared = sorted(node._parameters)  # noqa: SLF001 - rclpy keeps no public list of names
        hints = []
        for name in said:
            near = difflib.get_close_matches(name, declared, n=1)
            hints.append(f"{name} (did you mean {near[0]}?)" if near else name)
        node.get_logger().warning(f"ignoring parameter(s) this node does not have: {', '.join(hints)}; "
                                  "its parameters: docs/parameters.md")
    return unknown


def result(ok: bool, reason: str = "") -> SetParametersResult:
    return SetParametersResult(successful=ok, reason=reason)


def fixed_at_start(params, dynamic=()):
    """Reject runtime changes of parameters that only take effect at start."""
    fixed = [p.name for p in params if p.name not in dynamic]
    if fixed:
        return result(False, f"{', '.join(fixed)}: fixed at start; restart the node to change")
    return result(True)
