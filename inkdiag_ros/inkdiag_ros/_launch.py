"""The nodes' console entry points: a stop during start-up ends the process with status 0.

Importing a node's module (rclpy, numpy, scipy, scikit-learn, numba) takes seconds: 3.3-3.7 s
per node here (``python -c "import inkdiag_ros.fdi_node"`` and the others, 2026-11-27, beside a test
run), more on a loaded machine. Python's own handlers
would turn a Ctrl-C in that time into a ``KeyboardInterrupt`` traceback (exit status 130) and
a SIGTERM into status 143, where a running node stops with 0 (``docs/nodes.md``). Each entry
point here ends the process with status 0 on either signal while it imports its node, then
gives the signals back to Python's handlers and runs the node, which installs its own
(:func:`inkdiag_ros._spin.stop_on_signals`).
(``python -m inkdiag_ros.<node>`` imports before any code of ours runs: it keeps Python's.)
"""

from __future__ import annotations

import contextlib
import functools
import importlib
import signal
import sys


@contextlib.contextmanager
def stop_means_exit_0():
    """Within: SIGINT and SIGTERM raise ``SystemExit(0)`` (``finally`` blocks run), also when that exit leaves the
    block as another exception (:func:`came_from_a_stop`: an ``ImportError`` from rclpy's C extension's init);
    any other error after a stop goes on up as it is. A signal the process was started ignoring (a
    shell's background job: SIGINT) is taken too, as the running node takes it
    (:func:`inkdiag_ros._spin.stop_on_signals`, and rclpy): ``fdi ... &`` then ``kill -INT`` stopped a running node
    but not one still importing, which ran on (helper-85's QA). The handlers before it are back after it (inside, a
    node's own may replace them for a while, as :func:`inkdiag_ros._spin.stop_on_signals` does, restoring these).

    Where the handler's ``SystemExit`` lands in code whose exceptions Python ignores (a weakref
    callback of the import machinery: "Exception ignored in ... _get_module_lock", seen once in a
    CI run), it is not printed, and the process exits at the end of the block instead; a
    :func:`inkdiag_ros._spin.stop_on_signals` entered after that within the block starts with the stop
    requested (``inkdiag printer`` runs until stopped inside this block: a CI run's printer, whose
    SIGTERM was swallowed as it imported, ran on until killed)."""
    asked = []

    def stop(signum, frame):  # noqa: ARG001 - a signal handler's signature
        asked.append(signum)
        raise SystemExit(0)

    stop.asked = asked  # what a handler installed over this one reads (stop_on_signals: a stop already asked)

    def unraisable(u, hook=sys.unraisablehook):  # the ignored SystemExit: not a traceback on the way out
        if not isinstance(u.exc_value, SystemExit):
            hook(u)

    old = {sig: signal.signal(sig, stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    old_hook, sys.unraisablehook = sys.unraisablehook, unraisable
    try:
        yield
    except BaseException as exc:
        if asked and came_from_a_stop(exc):  # the stop's SystemExit on its way out, maybe as another exception
            raise SystemExit(0) from None
        raise
    finally:
        sys.unraisablehook = old_hook
        for sig, handler in old.items():
            signal.signal(sig, handler)
    if asked:  # the stop's SystemExit was swallowed on the way (above): exit now
        raise SystemExit(0)


def in_chain(exc: BaseException | None, *types) -> bool:
    """Whether ``exc`` or one of its causes (``__cause__``, else ``__context__``, in turn) is of one of ``types``."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, types):
            return True
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return False


def came_from_a_stop(exc: BaseException) -> bool:
    """Whether ``exc`` is a stop's ``SystemExit`` or ``KeyboardInterrupt``, has one in its chain of causes, or is an
    ``ImportError``: pybind11 turns whatever a module's init raises into an ``ImportError`` ("initialization
    failed", the cause attached), and rclpy's ``rpyutils`` re-raises it as "The C extension ... isn't present"
    (a SIGTERM 0.12 s after ``inkdiag printer``'s header line: a traceback and status 1)."""
    return in_chain(exc, SystemExit, KeyboardInterrupt, ImportError)


def _run(module: str):
    with stop_means_exit_0():
        main = importlib.import_module(f"inkdiag_ros.{module}").main
    return main()  # with Python's handlers, as without this module, until the node installs its own


def _console(module: str):
    """A console script: :func:`_run`, then the process ends as ``python -m`` ends it
    (:func:`inkdiag_ros._spin.exit_now`: the nodes down, not the interpreter's teardown too)."""
    status = _run(module)
    from ._spin import exit_now

    exit_now(status)


# the console scripts of inkdiag_ros/setup.py (`inkdiag` itself imports little before it parses its arguments)
loopback = functools.partial(_console, "loopback")
printhead_sim = functools.partial(_console, "printhead_sim")
fdi = functools.partial(_console, "fdi_node")
fe = functools.partial(_console, "fe_node")
record_baseline = functools.partial(_console, "baseline_node")
graph = functools.partial(_console, "graph")
echo = functools.partial(_console, "echo")
