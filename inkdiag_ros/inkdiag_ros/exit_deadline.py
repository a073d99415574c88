"""A process exit deadline that needs no GIL: a node process's bound on its own teardown.

Destroying the last node deletes the Fast DDS participant, and Fast DDS 2.14's
``DomainParticipant::set_listener(nullptr)`` (called by rmw_fastrtps on the way) can
livelock: it spins, holding the participant's listener mutex, until no discovery callback
is in flight, while the one in flight (a peer's endpoint going away, typically a peer
process shutting down at the same moment) waits for that mutex to finish. The main thread
spins inside rclpy with the GIL held, so no Python thread, timer or signal handler can
run; ``py-spy``/``gdb`` showed it more than 8 s in, in about 1 of 100 simultaneous
shutdowns of the three node processes on two cores.

:func:`exit_deadline` arms a POSIX timer whose expiry runs ``_exit(status)`` on a thread
of its own (``SIGEV_THREAD``), outside Python; :mod:`faulthandler` prints every thread's
stack just before, so the exit is not silent. Linux/glibc only; elsewhere it arms nothing.
"""

from __future__ import annotations

import contextlib
import ctypes
import faulthandler
import sys

_CLOCK_MONOTONIC = 1
_SIGEV_THREAD = 2
_STACKS_LEAD_S = 0.25  # the stacks are printed this much before the exit


class _Sigval(ctypes.Union):
    _fields_ = [("sival_int", ctypes.c_int), ("sival_ptr", ctypes.c_void_p)]


class _Sigevent(ctypes.Structure):  # glibc's struct sigevent (64 bytes on LP64)
    _fields_ = [("sigev_value", _Sigval), ("sigev_signo", ctypes.c_int), ("sigev_notify", ctypes.c_int),
                ("sigev_notify_function", ctypes.c_void_p), ("sigev_notify_attributes", ctypes.c_void_p),
                ("_pad", ctypes.c_byte * 32)]


class _Timespec(ctypes.Structure):
    _fields_ = [("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long)]


class _Itimerspec(ctypes.Structure):
    _fields_ = [("it_interval", _Timespec), ("it_value", _Timespec)]


def _libc():
    if not sys.platform.startswith("linux") or ctypes.sizeof(ctypes.c_void_p) != 8:
        return None
    for name in (None, "librt.so.1"):  # glibc >= 2.34 has the timers in libc itself
        try:
            lib = ctypes.CDLL(name, use_errno=True)
            lib.timer_create, lib.timer_settime, lib.timer_delete, lib._exit  # noqa: B018
            return lib
        except (OSError, AttributeError):
            continue
    return None


def _arm(seconds: float, status: int):
    lib = _libc()
    if lib is None:
        return None
    event = _Sigevent()
    event.sigev_notify = _SIGEV_THREAD
    event.sigev_value.sival_int = int(status)  # _exit(int) reads the sigval's low word
    event.sigev_notify_function = ctypes.cast(lib._exit, ctypes.c_void_p).value
    timer = ctypes.c_void_p()
    if lib.timer_create(_CLOCK_MONOTONIC, ctypes.byref(event), ctypes.byref(timer)) != 0:
        return None
    whole = int(seconds)
    when = _Itimerspec(_Timespec(0, 0), _Timespec(whole, int((seconds - whole) * 1e9)))
    if lib.timer_settime(timer, 0, ctypes.byref(when), None) != 0:
        lib.timer_delete(timer)
        return None
    return lib, timer


def check_seconds(seconds: float) -> float:
    """``seconds`` if it is a usable deadline (finite, > 0.5 s); else ``ValueError``."""
    if not 0.5 < seconds < float("inf"):
        raise ValueError(f"exit deadline must be a finite number of seconds > 0.5, got {seconds!r}")
    return seconds


@contextlib.contextmanager
def exit_deadline(seconds: float, status: int = 0):
    """Within the block, the process ends with exit status ``status`` once ``seconds`` have passed.

    Parameters
    ----------
    seconds : float
        The deadline from entering the block, s (> 0.5).
    status : int
        The exit status if the deadline passes: the one the process would have returned
        (its work was done before the teardown began).

    Yields
    ------
    bool
        Whether the deadline is armed (Linux/glibc only). Leaving the block disarms it.
        ``sys.stdout`` and ``sys.stderr`` are flushed on entering; ``_exit`` flushes
        nothing written after.

    Only a process's own entry point may use it: it ends the whole process, whatever else
    runs in it (a test runner included).
    """
    check_seconds(seconds)
    for stream in (sys.stdout, sys.stderr):  # _exit flushes nothing
        try:
            stream.flush()
        except (AttributeError, OSError, ValueError):
            pass
    armed = _arm(seconds, status)
    stacks = False
    if armed is not None:
        try:
            faulthandler.dump_traceback_later(seconds - _STACKS_LEAD_S, file=sys.stderr)
            stacks = True
        except (ValueError, OSError, AttributeError, RuntimeError):  # no usable stderr: exit without the stacks
            pass
    try:
        yield armed is not None
    finally:
        if stacks:
            faulthandler.cancel_dump_traceback_later()
        if armed is not None:
            lib, timer = armed
            lib.timer_delete(timer)
