"""The one console-entry body every inkdiag node shares."""

import rclpy
from rclpy.executors import ExternalShutdownException

from .allocator import keep_freed_memory


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
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0
