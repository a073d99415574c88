"""echo: print messages of an inkdiag topic as ``ros2 topic echo`` does (there is no ros2 CLI here).

    python -m inkdiag_ros.echo labels --namespace /head_00 [--once] [--max-items 128]

Topics: traces, ground_truth, labels, drying_nozzles, fm_estimates,
fm_estimates/array, /diagnostics (types and QoS from msg_defs). Messages are
printed as YAML in ros2's layout, each followed by ``---``; arrays longer
than ``--max-items`` are cut with ``'...'`` (ros2's ``--truncate-length``).
"""

from __future__ import annotations

import os
import sys

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.utilities import remove_ros_args

import msg_defs
from msg_defs import topics

from ._spin import exit_now, ros_args_error, stop_on_signals
from .cli import OneLineParser

TYPES = {
    topics.TRACES: (msg_defs.TRACE_MSG_TYPE, msg_defs.TRACES_QOS),
    topics.GROUND_TRUTH: (msg_defs.TRUTH_MSG_TYPE, msg_defs.RELIABLE_QOS),
    topics.LABELS: (msg_defs.LABELS_MSG_TYPE, msg_defs.RELIABLE_QOS),
    topics.DRYING_NOZZLES: (msg_defs.DRYING_MSG_TYPE, msg_defs.RELIABLE_QOS),
    topics.FM_ESTIMATES: (msg_defs.ESTIMATES_MSG_TYPE, msg_defs.RELIABLE_QOS),
    topics.FM_ESTIMATES_ARRAY: (msg_defs.ESTIMATES_ARRAY_MSG_TYPE, msg_defs.RELIABLE_QOS),
    topics.DIAGNOSTICS: (msg_defs.DIAGNOSTICS_MSG_TYPE, msg_defs.DIAGNOSTICS_QOS),
}


def _scalar(v) -> str:
    if isinstance(v, str):
        plain = v and not any(ch in v for ch in ":{}[],#'\"&*!|>%@`") and v.strip() == v
        try:
            float(v)
            plain = False  # a number-like string is quoted, as YAML needs
        except ValueError:
            pass
        return v if plain else "'" + v.replace("'", "''") + "'"
    if isinstance(v, bytes):  # a byte field (a DiagnosticStatus's level): its characters, as ros2 prints them
        import yaml

        return yaml.safe_dump({"v": "".join(map(chr, v))}, width=float("inf"))[3:].rstrip("\n")  # b'\x01': "\x01"
    if isinstance(v, float):
        return repr(v)
    return str(v)


def to_yaml(msg, indent: int = 0, max_items: int = 16) -> str:
    """YAML of a ROS message in the layout of ``ros2 topic echo``."""
    pad = "  " * indent
    lines = []
    for name in msg.get_fields_and_field_types():
        v = getattr(msg, name)
        if hasattr(v, "get_fields_and_field_types"):
            lines.append(f"{pad}{name}:")
            lines.append(to_yaml(v, indent + 1, max_items))
        elif isinstance(v, (list, tuple)) or hasattr(v, "tolist") or type(v).__name__ == "array":
            items = list(v[:max_items + 1]) if len(v) else []
            if not items:
                lines.append(f"{pad}{name}: []")
                continue
            lines.append(f"{pad}{name}:")
            for it in items[:max_items]:
                if hasattr(it, "get_fields_and_field_types"):
                    sub = to_yaml(it, 0, max_items)
                    lines.append(f"{pad}- " + sub.replace("\n", "\n" + pad + "  "))
                else:
                    lines.append(f"{pad}- {_scalar(it)}")
            if len(v) > max_items:
                lines.append(f"{pad}- '...'")
        else:
            lines.append(f"{pad}{name}: {_scalar(v)}")
    return "\n".join(lines)


def main(args=None) -> int:
    argv = list(sys.argv if args is None else args)
    ap = OneLineParser(prog="inkdiag_echo", description=__doc__.splitlines()[0])  # errors: one line, as the verbs'
    ap.add_argument("topic", choices=sorted(TYPES))
    ap.add_argument("--namespace", default="/head_00")
    ap.add_argument("--once", action="store_true")
    ap.add_argument("--max-items", type=int, default=128)  # ros2 topic echo's --truncate-length
    if why := ros_args_error(argv):
        ap.error(why)
    ns = ap.parse_args(remove_ros_args(argv)[1:])
    done = []
    mtype, qos = TYPES[ns.topic]

    gone = []  # the output's reader stopped (`| head`): echo ends quietly, as at --once

    def on_msg(msg):
        if (ns.once and done) or gone:
            return
        try:
            print(to_yaml(msg, max_items=ns.max_items) + "\n---", flush=True)
        except BrokenPipeError:  # no traceback, here or at exit (what is left in stdout's buffer goes nowhere)
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            gone.append(1)
        done.append(1)

    with stop_on_signals() as stop:  # a stop while rclpy starts ends it with 0, as the nodes (_spin.spin_node)
        rclpy.init(args=argv)
        node = None
        try:
            node = Node("echo", namespace=ns.namespace)
            stop.attach(node)
            node.create_subscription(mtype, ns.topic, on_msg, qos)
            while rclpy.ok() and not stop.requested and not (ns.once and done) and not gone:
                rclpy.spin_once(node, timeout_sec=0.1)
        except (KeyboardInterrupt, ExternalShutdownException):
            pass
        except Exception:  # a signal while the node was built: rclpy invalidated what it was building
            if not stop.explains_an_error():
                raise
        finally:
            if node is not None:
                node.destroy_node()
            rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    exit_now(main())  # the nodes down: not the interpreter's teardown too
