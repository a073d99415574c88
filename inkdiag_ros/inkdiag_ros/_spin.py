"""The one console-entry body every inkdiag node shares."""

import contextlib
import os
import signal
import sys
import threading
import time

import rclpy
from rclpy.exceptions import ParameterException
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


def _no_keyboard_interrupt(signum, frame):  # rclpy's own handler does the work
    pass


@contextlib.contextmanager
def sigint_as_shutdown():
    """Make Ctrl-C (SIGINT) shut rclpy down the way SIGTERM does.

    Enter it just before ``rclpy.init``: rclpy's signal handler then shuts the
    context down and wakes the executor (which raises ``ExternalShutdownException``),
    and Python raises no ``KeyboardInterrupt``. A ``KeyboardInterrupt`` raised in
    the middle of rclpy's executor internals left entity handles half-released,
    and destroying the nodes afterwards crashed the process (SIGSEGV) in about
    one Ctrl-C in twenty here. The previous handler is restored on exit.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.signal(signal.SIGINT, _no_keyboard_interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)


def spin_node(node_cls, args=None, *, until=None, exit_code=None, prog=None) -> int:
    """Init rclpy, spin one ``node_cls()`` until Ctrl-C / SIGTERM / shutdown, clean up.

    ``until(node)``: stop spinning once it is true (default: never). ``exit_code(node)``:
    the process's exit status after a normal stop (default 0). A node that refuses its
    parameters (``ValueError`` or rclpy's ``ParameterException`` while it is built) is
    reported in one line on stderr, exit status 2, no traceback.
    """
    keep_freed_memory()
    prog = prog or os.path.basename(sys.argv[0] or "node")
    with sigint_as_shutdown():
        rclpy.init(args=args)
        node = None
        try:
            try:
                node = node_cls()
            except (ValueError, ParameterException) as exc:
                print(f"{prog}: {exc}", file=sys.stderr)
                return 2
            if until is None:
                rclpy.spin(node)
            else:
                while rclpy.ok() and not until(node):
                    rclpy.spin_once(node, timeout_sec=0.1)
        except (KeyboardInterrupt, ExternalShutdownException):
            pass
        except Exception:
            if node is None or not shutting_down(node.context):
                raise
        finally:
            if node is not None:
                node.destroy_node()
            rclpy.try_shutdown()
    return 0 if exit_code is None else exit_code(node)
