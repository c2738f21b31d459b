"""A Dask distributed client for a scheduler address, with a bounded wait.

``distributed.Client(address, timeout=...)`` waits for ever when the address answers TCP but is
not a Dask scheduler (the dashboard's HTTP port is the usual slip): the HTTP server waits for a
request line that never comes, and the client for a handshake that never comes. :func:`connect`
first asks the address who it is, under a deadline, and only then creates the client. A
scheduler without workers accepts work and holds it for ever: :func:`connect` with ``workers``
warns and waits for them under the same deadline.

Dask is an optional extra (``pip install 'cilia-flow[dask]'``): without it, a scheduler address
is a :class:`SchedulerError` that names the extra.
"""
from __future__ import annotations

import asyncio
import logging
import math
import os

__all__ = ["SchedulerError", "connect", "DEFAULT_TIMEOUT", "TIMEOUT_ENV", "EXTRA"]

logger = logging.getLogger(__name__)

DEFAULT_TIMEOUT = 20.0
"""Seconds to wait for a scheduler to answer (override: ``timeout=``, or :data:`TIMEOUT_ENV`)."""
TIMEOUT_ENV = "CILIA_SCHEDULER_TIMEOUT"
EXTRA = "pip install 'cilia-flow[dask]'"
"""The install command of the optional extra that brings dask and distributed."""


class SchedulerError(OSError):
    """A scheduler address that does not lead to a Dask scheduler in time, or Dask not installed;
    the message names the address or the extra."""


def _distributed():
    """The ``distributed`` package; :class:`SchedulerError` naming :data:`EXTRA` when it is not installed."""
    try:
        import distributed
        import distributed.comm
    except ImportError as exc:
        raise SchedulerError(f"a Dask scheduler needs the packages dask and distributed ({exc}): {EXTRA}") from None
    return distributed


def timeout_from(value: float | None) -> float:
    """``value``, else the environment's :data:`TIMEOUT_ENV`, else :data:`DEFAULT_TIMEOUT`;
    a ValueError for a value that is not a positive finite number of seconds."""
    if value is None:
        env = os.environ.get(TIMEOUT_ENV, "").strip()
        if not env:
            return DEFAULT_TIMEOUT
        try:
            value = float(env)
        except ValueError:
            raise ValueError(f"{TIMEOUT_ENV}={env!r} is not a number of seconds") from None
    value = float(value)
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"the scheduler timeout must be a positive number of seconds, got {value:g}")
    return value


async def _identity(address: str, timeout: float) -> dict:
    comm = await _distributed().comm.connect(address, timeout=timeout)
    try:
        await comm.write({"op": "identity"})
        return await comm.read()
    finally:
        comm.abort()


def _in_own_loop(make):
    """Run the coroutine ``make()`` to completion on a fresh event loop in its own thread (the
    caller may already run a loop, e.g. in Jupyter)."""
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(1, thread_name_prefix="scheduler-probe") as ex:
        return ex.submit(lambda: asyncio.run(make())).result()


def _hint(address: str) -> str:
    return (f"is {address} the scheduler's address (tcp://HOST:8786 by default), not its dashboard (HTTP, "
            f"port 8787)?")


def probe(address: str, timeout: float | None = None) -> dict:
    """The identity of the Dask scheduler at ``address``; :class:`SchedulerError` when there is
    none, or it does not answer within ``timeout`` seconds (:func:`timeout_from`)."""
    t = timeout_from(timeout)
    try:
        ident = _in_own_loop(lambda: asyncio.wait_for(_identity(address, t), t))
    except (asyncio.TimeoutError, TimeoutError):
        raise SchedulerError(f"{address} did not answer as a Dask scheduler within {t:g} s: {_hint(address)} "
                             f"(--scheduler-timeout sets the wait)") from None
    except (OSError, ValueError, TypeError) as exc:  # refused, unreachable, a malformed address
        msg = " ".join(str(exc).split()) or type(exc).__name__
        raise SchedulerError(f"cannot reach a Dask scheduler at {address}: {msg}") from None
    if not isinstance(ident, dict) or ident.get("type") != "Scheduler":
        what = ident.get("type") if isinstance(ident, dict) else type(ident).__name__
        raise SchedulerError(f"{address} is not a Dask scheduler (it answered as {what!r}): {_hint(address)}")
    return ident


def connect(address: str, timeout: float | None = None, *, workers: int = 0):
    """A ``distributed.Client`` for the scheduler at ``address``, after :func:`probe` found one
    there within ``timeout`` seconds; raises :class:`SchedulerError` otherwise.

    With ``workers`` >= 1, the scheduler must also have that many workers, or get them within
    ``timeout`` seconds: a warning says so when it has fewer (work sent to a scheduler without
    workers waits for ever), and a :class:`SchedulerError` ends the wait (the client closed)."""
    distributed = _distributed()
    t = timeout_from(timeout)
    ident = probe(address, t)
    logger.info("connecting to the Dask scheduler at %s", address)
    client = distributed.Client(address, timeout=t)
    if workers < 1:
        return client
    have = len(ident.get("workers") or {})
    try:
        have = len(client.scheduler_info().get("workers") or {})
    except Exception:  # noqa: BLE001 -- the identity's count then
        pass
    if have >= workers:
        return client
    logger.warning("the Dask scheduler at %s has %d worker(s); waiting up to %g s for %d (--scheduler-timeout "
                   "sets the wait)", address, have, t, workers)
    try:
        client.wait_for_workers(workers, timeout=t)
    except (TimeoutError, asyncio.TimeoutError, OSError):
        client.close()
        raise SchedulerError(f"the Dask scheduler at {address} has no workers (none joined within {t:g} s): start "
                             f"some with `dask worker {address}`, or raise --scheduler-timeout") from None
    except BaseException:
        client.close()
        raise
    return client
