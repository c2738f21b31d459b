"""Termination signals handled like Ctrl-C.

``kill``, Slurm, systemd and Docker stop a program with SIGTERM; a closed terminal sends SIGHUP.
Python's default for both is to die at once, without running any ``finally`` or ``except``
clause: worker processes are orphaned and staging files stay behind. :func:`terminate_as_interrupt`
installs handlers that raise :class:`Terminated` -- a :class:`KeyboardInterrupt` -- in the main
thread instead, so the cleanup that Ctrl-C runs (stop the workers, remove the staging folder)
runs for these signals too, and the command line exits with ``128 + signum`` (143 for SIGTERM,
129 for SIGHUP, 130 for Ctrl-C).

An exception raised inside a callback from native code is swallowed there, and the native code
goes on with a broken result: a signal that lands while numba compiles (llvmlite's object-cache
callback) then crashes the process with a segmentation fault. The handlers therefore raise only
where no frame of such a callback is on the stack, and otherwise deliver the signal again 50 ms
later. Ctrl-C (SIGINT) gets the same treatment.

Compiled code (numba) can also call back into the interpreter while it runs: the first call of a
kernel that uses BLAS or LAPACK looks the routines up in SciPy from native code. A handler that
raises there leaves the native code going on with a broken result (a segmentation fault, or
``SystemError: CPUDispatcher(...) returned a result with an exception set``). Calls into such
kernels are therefore marked with :func:`native_call`; a signal that arrives inside one is
delivered again 50 ms later, until the call has returned.

A process forked from one with these handlers (a ``fork`` pool worker) must not inherit them:
its parent stops it with SIGTERM and expects it to die at once, even inside native code. The
handlers are therefore reset to the defaults in a forked child (:func:`os.register_at_fork`),
and a handler that still runs in another process acts as the default would.

:func:`signals_held` holds SIGINT, SIGTERM and SIGHUP back around a critical section (an output
folder's swap): they take effect, as they would have, once it ends.
"""
from __future__ import annotations

import logging
import os
import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["Terminated", "TERMINATING", "terminate_as_interrupt", "exit_status", "describe", "native_call",
           "interrupt_of", "signals_held"]

logger = logging.getLogger(__name__)

TERMINATING: tuple[signal.Signals, ...] = tuple(
    s for s in (getattr(signal, "SIGTERM", None), getattr(signal, "SIGHUP", None)) if s is not None)

_RETRY_S = 0.05
_CALLBACK_MODULES = (f"{os.sep}llvmlite{os.sep}", f"{os.sep}ctypes{os.sep}")  # native code calling back


_ACTIVE: dict[int, dict] = {}  # per active block: {signal: the handler it replaced}
_NATIVE = [0]  # depth of the main thread's calls into compiled code (native_call)


@contextmanager
def native_call() -> Iterator[None]:
    """Mark a call into compiled code made by the main thread: a signal that arrives while it
    runs is delivered again once it has returned (see the module docstring). Other threads
    receive no signals; there it does nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    _NATIVE[0] += 1
    try:
        yield
    finally:
        _NATIVE[0] -= 1


def interrupt_of(exc: BaseException | None) -> KeyboardInterrupt | None:
    """The interrupt behind ``exc``: ``exc`` itself if it is a KeyboardInterrupt, or the one that
    a SystemError saying a compiled function "returned a result with an exception set" carries as
    its cause (a signal handled inside compiled code); None otherwise."""
    for _ in range(8):
        if isinstance(exc, KeyboardInterrupt):
            return exc
        if not isinstance(exc, SystemError):
            return None
        exc = exc.__cause__ or exc.__context__
    return None


def _reset_in_child() -> None:
    """After a fork: the child gets the default actions back for the signals the parent handles."""
    for s in set().union(*_ACTIVE.values()) if _ACTIVE else ():
        try:
            signal.signal(s, signal.default_int_handler if s == signal.SIGINT else signal.SIG_DFL)
        except (OSError, ValueError):
            pass
    _ACTIVE.clear()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_reset_in_child)


def _in_native_callback(frame) -> bool:
    """Whether ``frame`` or a caller runs a callback from native code (an exception raised there
    would be swallowed by the native caller)."""
    while frame is not None:
        if any(m in frame.f_code.co_filename for m in _CALLBACK_MODULES):
            return True
        frame = frame.f_back
    return False


class Terminated(KeyboardInterrupt):
    """A termination signal (SIGTERM, SIGHUP) received by the process.

    A subclass of :class:`KeyboardInterrupt`, so that every ``except KeyboardInterrupt`` cleanup
    also runs for it.

    Parameters
    ----------
    signum : int
        The signal's number.
    """

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = int(signum)

    def __str__(self) -> str:
        return f"terminated by {describe(self.signum)}"

    def __reduce__(self):
        return (type(self), (self.signum,))


def describe(signum: int) -> str:
    """``"SIGTERM"`` for 15, and so on (``"signal N"`` for an unknown number)."""
    try:
        return signal.Signals(signum).name
    except ValueError:
        return f"signal {signum}"


def exit_status(exc: KeyboardInterrupt) -> int:
    """The conventional exit status of a process stopped by ``exc``: ``128 + signum`` for a
    :class:`Terminated`, 130 (SIGINT) for Ctrl-C."""
    return 128 + (exc.signum if isinstance(exc, Terminated) else int(signal.SIGINT))


@contextmanager
def terminate_as_interrupt(signals: tuple = TERMINATING) -> Iterator[None]:
    """Within the block, ``signals`` raise :class:`Terminated` in the main thread of this process,
    and SIGINT raises :class:`KeyboardInterrupt` as usual, both at a safe point (see the module
    docstring).

    The first terminating signal raises; later ones (while the cleanup runs) are ignored, so that
    a second SIGTERM cannot cut the cleanup short (SIGKILL still stops the process). Outside the
    main thread this does nothing (Python delivers signals to the main thread only). The previous
    handlers are restored on exit.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    owner = os.getpid()
    fired: list[int] = []

    def handler(signum, frame):
        if os.getpid() != owner:  # a forked child that inherited the handler: act as by default
            if signum == signal.SIGINT:
                raise KeyboardInterrupt
            signal.signal(signum, signal.SIG_DFL)
            os.kill(os.getpid(), signum)
            return
        if signum != signal.SIGINT and fired:
            return
        if _NATIVE[0] or _in_native_callback(frame):  # not here: again in a moment
            timer = threading.Timer(_RETRY_S, os.kill, (owner, signum))
            timer.daemon = True
            timer.start()
            return
        if signum == signal.SIGINT:
            raise KeyboardInterrupt
        fired.append(signum)
        raise Terminated(signum)

    old = {}
    ours = tuple(signals) + ((signal.SIGINT,) if signal.getsignal(signal.SIGINT) is signal.default_int_handler else ())
    for s in ours:  # (an ignored SIGINT, e.g. under nohup, stays ignored)
        try:
            old[s] = signal.signal(s, handler)
        except (OSError, ValueError):  # not settable here
            continue
    _ACTIVE[id(old)] = old
    try:
        yield
    finally:
        _ACTIVE.pop(id(old), None)
        for s, h in old.items():
            try:
                signal.signal(s, h if h is not None else signal.SIG_DFL)
            except (OSError, ValueError, TypeError):
                pass


_HELD = tuple(s for s in (getattr(signal, n, None) for n in ("SIGINT", "SIGTERM", "SIGHUP")) if s is not None)


@contextmanager
def signals_held() -> Iterator[None]:
    """Hold SIGINT, SIGTERM and SIGHUP back within the block: they take effect when it ends.

    In the main thread, the block's own handlers note the signals (any thread of the process may
    receive them -- numba's and BLAS's threads do -- but Python runs handlers in the main thread
    only), and on leaving, the previous handlers are restored and each noted signal is raised
    again: Ctrl-C's KeyboardInterrupt, :func:`terminate_as_interrupt`'s :class:`Terminated`, or
    the default action (death by SIGTERM) then happens with the block's work whole. Elsewhere the
    signals are blocked in this thread (:func:`signal.pthread_sigmask`; where there is none,
    nothing is held)."""
    if threading.current_thread() is not threading.main_thread():
        if not hasattr(signal, "pthread_sigmask"):
            yield
            return
        old = signal.pthread_sigmask(signal.SIG_BLOCK, _HELD)
        try:
            yield
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, old)
        return
    noted: list[int] = []
    saved = {}
    for s in _HELD:
        h = signal.getsignal(s)
        if h is not None:  # None: a handler not installed from Python; it cannot be restored, so left alone
            saved[s] = h
            signal.signal(s, lambda signum, frame: noted.append(signum))
    try:
        yield
    finally:
        for s, h in saved.items():
            signal.signal(s, h)
        for signum in dict.fromkeys(noted):
            logger.info("signal %d held back until the block had ended", signum)
            signal.raise_signal(signum)
