"""The one console-entry body every inkdiag node shares."""

import contextlib
import gc
import os
import signal
import sys
import threading
import time

import rclpy
import rclpy.signals
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor

from ._fatal import FatalNodeError
from .allocator import PeriodicRelease, keep_freed_memory
from .blas import limit_blas_threads
from .exit_deadline import check_seconds, exit_deadline

TEARDOWN_DEADLINE_S = 5.0  # a node process exits at the latest this long after its spin loop stopped


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


def exit_now(status) -> None:
    """End a node process with ``status`` once its own teardown is done, without the interpreter's.

    ``sys.exit(status)`` then tears every module and object down (numpy, scipy, scikit-learn, numba,
    rclpy, a model): 0.2-0.5 s after a node's last line here, 1.0-1.5 s with four busy processes on the
    two cores, most of the time a stopped ``graph`` took to exit (2.0-2.6 s in a CI run, against its 2 s
    bound; its own teardown took 0.05-0.09 s of it). Here stdout and stderr are flushed and the process
    ends at once (``os._exit``): for the ``__main__`` of a node module and the console scripts, after
    :func:`spin_node` (or the runner's own teardown) has destroyed the nodes, closed their outputs and
    shut rclpy down. A status ``sys.exit`` would print (not an int or None) goes to ``sys.exit``.
    """
    if status is not None and not isinstance(status, int):
        sys.exit(status)
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except Exception:  # noqa: BLE001 - a closed or broken stream: nothing more to write to it
            pass
    os._exit(status or 0)


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
    one Ctrl-C in twenty here. SIGTERM gets the same no-op Python handler, so that once
    rclpy's handlers are uninstalled for the teardown (:func:`quiet_signal_handling`) a
    second SIGTERM cannot kill the process while it closes a bag. The previous handlers
    are restored on exit.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = {sig: signal.signal(sig, _no_keyboard_interrupt) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)


class StopRequest:
    """What :func:`stop_on_signals` hands back: whether a SIGINT/SIGTERM arrived.

    ``requested`` is set by a Python-level handler (it runs in the main thread), which
    also triggers the guard condition :meth:`attach` put on a node: the executor then
    has work (that guard condition's no-op callback), ``spin_once`` returns and the
    spin loop sees ``requested``.
    """

    def __init__(self):
        self.requested = False
        self._gc = None

    def attach(self, node):
        """Give ``node`` the guard condition a signal triggers (destroyed with the node)."""
        self._gc = node.create_guard_condition(_no_op)
        if self.requested:  # a signal while the node was being built
            self._gc.trigger()

    def explains_an_error(self, context=None) -> bool:
        """Whether an error just raised is this stop's doing: a signal arrived, or ``context`` (default: rclpy's
        default context) is or soon goes down (:func:`shutting_down`), as when a signal invalidates the context
        under a node being built (RCLError) or a callback publishing."""
        return self.requested or shutting_down(rclpy.utilities.get_default_context() if context is None else context)

    def _on_signal(self, signum, frame):
        self.requested = True
        gc = self._gc
        if gc is not None:
            try:
                gc.trigger()
            except Exception:  # destroyed with its node: nothing left to wake
                pass


def _no_op():
    pass


def _half_built(u) -> bool:
    """Whether an unraisable error is an rclpy object's finalizer missing an attribute its ``__init__`` never set."""
    module, name = getattr(u.object, "__module__", None), getattr(u.object, "__qualname__", None)
    return (u.exc_type is AttributeError and isinstance(module, str) and module.startswith("rclpy.")
            and isinstance(name, str) and name.endswith(".__del__"))


@contextlib.contextmanager
def stop_on_signals():
    """Record SIGINT and SIGTERM in a :class:`StopRequest`, for a spin loop that cannot miss them.

    Enter it just before ``rclpy.init`` (rclpy's own handlers then chain to these):
    Ctrl-C raises no ``KeyboardInterrupt`` (see :func:`sigint_as_shutdown`), and the
    spin loop learns of the signal from ``requested`` and a guard condition of its
    node, not only from the context going down. rclpy's signal thread triggers the
    executors' wake-up guard condition *before* it shuts the contexts down: an
    executor woken by it, finding no work and the context still ok, went back to
    waiting without a timeout: nothing wakes it again but traffic or a timer (issue 12:
    fe, which has no timer, ignored its first signal now and then). Handlers restored
    on exit.

    Entered where a handler that records stops (``asked``, as :func:`inkdiag_ros._launch.stop_means_exit_0`'s)
    has recorded one, the stop starts requested. After a stop, an ``AttributeError`` in the finalizer
    (``__del__``) of an rclpy object is not printed: an object a stop left half built (a
    ``SingleThreadedExecutor`` whose ``__init__`` met the context going down: "Exception ignored in
    ... Executor.__del__", an ``AttributeError`` traceback, in a CI run); other errors are.
    """
    stop = StopRequest()
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return
    old = {sig: signal.signal(sig, stop._on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    if any(getattr(h, "asked", None) for h in old.values()):  # _launch.stop_means_exit_0's, swallowed
        stop.requested = True  # (never set back: a signal may have landed since the install above)

    def unraisable(u, hook=sys.unraisablehook):
        if not (stop.requested and _half_built(u)):
            hook(u)

    old_hook, sys.unraisablehook = sys.unraisablehook, unraisable
    try:
        yield stop
    finally:
        sys.unraisablehook = old_hook
        for sig, handler in old.items():
            signal.signal(sig, handler)


def freeze_startup_objects() -> int:
    """Move every object alive now out of the cyclic garbage collector's reach (``gc.freeze``).

    A node process holds ~100,000 container objects once rclpy, numpy, scipy and its
    core are imported and the node is built; each full (generation-2) collection walks
    all of them (69 ms here) although none of them is ever garbage. py-spy (--native) put
    13 % of the fe node's samples in ``gc_collect_main`` in a soak (issue 12); side by side
    with main, the freeze and fe's serialized take together saved 2-3 % of fe's CPU per
    frame. Garbage is collected first; collections go on as before for the objects made
    later. Returns the number of frozen objects.
    """
    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()


def quiet_signal_handling() -> None:
    """Uninstall rclpy's signal handlers (and join their thread) before any entity is destroyed.

    On SIGINT/SIGTERM rclpy's own signal thread shuts every context down
    (``rcl_shutdown``) at a moment of its choosing, while the main thread, woken
    by the same signal, is already destroying the node's publishers and
    services. The two racing in Fast DDS crashed a node now and then (SIGSEGV in
    ``Service.destroy`` inside ``destroy_node``, about 1 Ctrl-C in 100 with
    three node processes on two cores; once a hang in ``destroy_node``).
    Uninstalling joins that thread, so nothing else touches the context from
    here on: the nodes go first, then :func:`rclpy.try_shutdown`. A signal after
    this reaches the Python handlers (:func:`stop_on_signals`) only.
    """
    rclpy.signals.uninstall_signal_handlers()


def tear_down(executor, nodes, *, context_is_ours: bool = True, deadline_s: float | None = None,
              deadline_status: int = 0) -> None:
    """Take a node process down in the one safe order: signals, executor, outputs, nodes, context.

    ``executor``: the executor (or ``None``); ``nodes``: the nodes to destroy
    (``None`` entries skipped). ``context_is_ours``: this code initialised rclpy's
    default context, so it uninstalls rclpy's signal handlers first
    (:func:`quiet_signal_handling`) and shuts the context down last; ``False``
    leaves both to the caller. A node's ``close_outputs()``, if it has one (its last
    results published, its files closed), runs once the executor is down, before any
    node is destroyed.

    ``deadline_s``: a process entry point's bound on destroying the nodes and the
    context, s: past it the process exits with ``deadline_status``
    (:func:`.exit_deadline.exit_deadline`: Fast DDS can livelock deleting its
    participant). The outputs are closed before the clock starts. ``None`` (the
    default): no bound; never give one from code that may run inside another program
    (a test runner).
    """
    if context_is_ours:
        quiet_signal_handling()
    if executor is not None:
        executor.shutdown()
    nodes = [n for n in nodes if n is not None]
    try:
        close_outputs(nodes)
    except FatalNodeError:  # a recording's last writes failed: the process's status is now its (spin_node)
        deadline_status = 2
        raise
    finally:  # a failed close (its error goes on up) never skips the bounded rest
        bound = contextlib.nullcontext() if deadline_s is None else exit_deadline(deadline_s, deadline_status)
        with bound:
            for node in nodes:
                node.destroy_node()
            if context_is_ours:
                rclpy.try_shutdown()


def close_outputs(nodes) -> None:
    """Call each node's ``close_outputs()`` (if it has one); one that raises does not stop the others."""
    errors = []
    for node in nodes:
        close = getattr(node, "close_outputs", None)
        if close is not None:
            try:
                close()
            except Exception as exc:  # noqa: BLE001 - raised below, after every node had its turn
                errors.append(exc)
    if errors:
        raise errors[0]


@contextlib.contextmanager
def _stderr_held():
    """The process's stderr (file descriptor 2, where rcl logs) into a temporary file meanwhile; yields a list
    that holds what was written there, once restored."""
    import tempfile

    sys.stderr.flush()
    written = []
    saved = os.dup(2)
    try:
        with tempfile.TemporaryFile() as held:
            os.dup2(held.fileno(), 2)
            try:
                yield written
            finally:
                os.dup2(saved, 2)
                held.seek(0)
                written.append(held.read())
    finally:
        os.close(saved)


def ros_args_error(argv) -> str | None:
    """Why rcl cannot parse the ROS arguments of ``argv`` (after ``--ros-args``), in one line; None if it can.

    A bad ``-p``, ``-r`` or ``--params-file`` (a missing file) made ``rclpy.init`` raise, a traceback
    with exit status 1, after rcl's own log line. Checked first, that log held back: the caller
    prints this one line and exits 2, as for a parameter the node refuses.
    """
    import ast
    import re

    from rclpy.utilities import remove_ros_args

    argv = [str(a) for a in argv]
    if "--ros-args" not in argv:
        return None

    def why_not():
        try:
            remove_ros_args(argv)
        except Exception as exc:  # noqa: BLE001 - rclpy's RCLInvalidROSArgsError, UnknownROSArgsError
            if type(exc).__name__ == "UnknownROSArgsError":  # its text: the list's repr, "['--foo']"
                try:
                    return "unknown ROS arguments: " + " ".join(map(str, ast.literal_eval(str(exc))))
                except (ValueError, SyntaxError, TypeError):
                    return f"unknown ROS arguments: {exc}"
            text = str(exc).strip()
            text = text.splitlines()[0] if text else type(exc).__name__
            why = "bad ROS arguments: " + re.sub(r",? at /\S+:\d+", "", text).removeprefix(
                "Failed to parse ROS arguments: ")
            if re.search(r"'-p [^']*:='", text):  # `-p name:=` (the shell ate the quotes of name:='')
                why += "; an empty string is written -p \"NAME:=''\""
            return why
        return None

    try:
        with _stderr_held() as written:
            why = why_not()
    except OSError:  # no temporary file, or no fd 2, to hold rcl's log in: it is not held back
        return why_not()
    if why is None and written[0]:  # parsed: whatever rcl said all the same goes out
        os.write(2, written[0])
    return why


def spin_node(node_cls, args=None, *, until=None, exit_code=None, prog=None, events: bool = False,
              teardown_deadline_s: float | None = TEARDOWN_DEADLINE_S) -> int:
    """Init rclpy, spin one ``node_cls()`` until Ctrl-C / SIGTERM / shutdown, clean up.

    ``until(node)``: stop spinning once it is true (default: never). ``exit_code(node)``:
    the process's exit status after a normal stop (default 0). A node that refuses its
    parameters (``ValueError`` or rclpy's ``ParameterException`` while it is built) is
    reported in one line on stderr, exit status 2, no traceback. A signal while the node
    is being built stops it there (exit 0, or 1 with ``exit_code``: it did nothing).

    BLAS libraries run one thread each (:func:`limit_blas_threads`). A SIGINT or SIGTERM
    stops the spin loop through :func:`stop_on_signals`; the loop also re-checks the
    context at least once a second (``until``: every 0.1 s), and every few seconds hands
    a drained backlog's free heap back to the system (:class:`.allocator.PeriodicRelease`).
    The objects of the built node and its imports are frozen out of the cyclic garbage
    collector before spinning (:func:`freeze_startup_objects`).

    ``events``: spin rclpy's C++ ``EventsExecutor`` (``rclpy.experimental``) instead of the
    Python ``SingleThreadedExecutor``: no wait set rebuilt in Python per wake-up (``scripts/bench
    take``: about 0.6 ms less CPU per taken 2 MB trace message here). It takes no guard
    condition: a signal reaches the loop through rclpy's shutdown, which wakes it, or its
    1 s timeout.

    A :class:`._fatal.FatalNodeError` out of a callback (a recording's disk is full) stops the loop: its
    message on one line (``PROG: ...``), the node torn down as after a signal, exit status 2.

    ``teardown_deadline_s``: once the loop has stopped, the process exits (with the status
    it would have returned) at the latest this long after, whatever the middleware does
    (:func:`tear_down`); ``None``: no bound. The default suits what this function is for,
    a node process's entry point; it ends the whole process.
    """
    if teardown_deadline_s is not None:  # a bad one fails here, not at the teardown
        check_seconds(teardown_deadline_s)
    argv = list(sys.argv if args is None else args)
    own = argv[1:argv.index("--ros-args")] if "--ros-args" in argv else argv[1:]
    if "-h" in own or "--help" in own:  # before rclpy: a node started for its help would join the graph
        from .paramdoc import node_help

        try:
            print(node_help(node_cls, prog or os.path.basename(argv[0] if argv else "node")), flush=True)
        except BrokenPipeError:  # `fdi --help | head`: the reader had enough; no traceback at exit either
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    prog = prog or os.path.basename(sys.argv[0] or "node")
    if why := ros_args_error(argv):
        print(f"{prog}: {why}", file=sys.stderr)
        return 2
    keep_freed_memory()
    release = PeriodicRelease()
    limit_blas_threads()
    with stop_on_signals() as stop:
        rclpy.init(args=args)
        node = executor = None
        early = None  # the status of a stop before spinning
        try:
            try:
                node = node_cls()
            except (ValueError, ParameterException) as exc:
                print(f"{prog}: {exc}", file=sys.stderr)
                early = 2
                return early
            except Exception:  # a signal while it was built: rclpy invalidated its publishers
                if not stop.explains_an_error():
                    raise
                early = 0 if exit_code is None else 1
                return early
            executor = make_executor([node], events, stop)
            freeze_startup_objects()
            period = 1.0 if until is None else 0.1
            while not stop.requested and node.context.ok() and not (until is not None and until(node)):
                executor.spin_once(timeout_sec=period)
                release()
        except (KeyboardInterrupt, ExternalShutdownException):
            pass
        except FatalNodeError as exc:  # the node cannot go on (a recording's full disk): one line, exit 2
            print(f"{prog}: {exc}", file=sys.stderr, flush=True)
            early = 2
        except Exception:
            if node is None or not stop.explains_an_error(node.context):
                raise
        finally:
            status = _deadline_status(early, exit_code, node)
            try:
                tear_down(executor, [node], deadline_s=teardown_deadline_s, deadline_status=status)
            except FatalNodeError as exc:  # a recording's last writes, as its node closed its outputs
                print(f"{prog}: {exc}", file=sys.stderr, flush=True)
                early = 2
    return early if early is not None else 0 if exit_code is None else exit_code(node)


def make_executor(nodes, events: bool, stop):
    """The executor that spins ``nodes`` (all of one context), each node added.

    ``events``: rclpy's C++ ``EventsExecutor``, which takes no guard condition (rclpy's
    shutdown wakes it); else the Python ``SingleThreadedExecutor``, with ``stop`` (a
    :func:`stop_on_signals` request) attached to the first node so that a signal wakes it.
    """
    ctx = nodes[0].context
    if events:
        from rclpy.experimental import EventsExecutor

        executor = EventsExecutor(context=ctx)
    else:
        stop.attach(nodes[0])
        executor = SingleThreadedExecutor(context=ctx)
    for n in nodes:
        executor.add_node(n)
    return executor


def _deadline_status(early, exit_code, node) -> int:
    """The exit status if the teardown deadline passes: the one the process would return.

    1 while an exception is on its way out (it would end the process with a traceback),
    the early return's status, else ``exit_code(node)`` (0 without one).
    """
    if sys.exc_info()[1] is not None:
        return 1
    if early is not None:
        return early
    try:
        return 0 if exit_code is None or node is None else int(exit_code(node))
    except Exception:  # noqa: BLE001 - asked again, and raised, after the teardown
        return 1


def take_queued(subscription, at_most: int, *, with_info: bool = False):
    """Messages already queued on ``subscription``, taken as rclpy's executor takes them.

    A subscription callback that drains its reader this way handles a burst (a head
    scan's nozzle-range messages) in one executor wake-up and wait-set rebuild instead
    of one per message. Yields at most ``at_most`` messages; ``with_info``: ``(message,
    info)`` pairs, ``info`` rmw's message info (a dict: ``received_timestamp``, ns, ...).
    """
    for _ in range(at_most):
        with subscription.handle:
            taken = subscription.handle.take_message(subscription.msg_type, subscription.raw)
        if taken is None:
            return
        yield taken if with_info else taken[0]


def take_into(subscription, at_most: int, handle) -> bool:
    """Each message :func:`take_queued` yields handed to ``handle(msg)`` in turn; whether there was any."""
    n = 0
    for msg in take_queued(subscription, at_most):
        handle(msg)
        n += 1
    return n > 0
