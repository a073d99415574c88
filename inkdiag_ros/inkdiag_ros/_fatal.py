"""An error that ends a node process with one line on stderr and exit status 2: no traceback.

No ROS in here: :mod:`inkdiag_ros.bags`, which the offline verbs import too, raises it.
"""


class FatalNodeError(Exception):
    """Raised by a node's callback when the process cannot go on (a recording's disk is full):
    :func:`inkdiag_ros._spin.spin_node` and the graph runner tear the nodes down as after a stop,
    print ``PROG: MESSAGE`` and exit with status 2."""
