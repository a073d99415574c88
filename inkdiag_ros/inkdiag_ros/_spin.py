"""The one console-entry body every inkdiag node shares."""

import time

import rclpy
from rclpy.executors import ExternalShutdownException

from .allocator import keep_freed_memory


def shutting_down(context, grace_s: float = 0.2) -> bool:
    """Whether ``context`` is (or within ``grace_s`` goes) down.

    A SIGINT/SIGTERM shuts the context down from rclpy's signal thread while a
    callback may be publishing; the callback's error (a publisher whose context
    became invalid) can reach the spinning thread a moment before the context
    reports it is down. An error followed by a shutdown is that shutdown, not
    a failure.
    """
    deadline = time.monotonic() + grace_s
    while context.ok():
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.01)
    return True


def spin_node(node_cls, args=None) -> int:
    """Init rclpy, spin one ``node_cls()`` until Ctrl-C / SIGTERM / shutdown, clean up."""
    keep_freed_memory()
    rclpy.init(args=args)
    node = None
    try:
        node = node_cls()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception:
        if node is None or not shutting_down(node.context):
            raise
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0
