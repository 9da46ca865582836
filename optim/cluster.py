"""The Dask client every distributed job of ours uses (cohort fits, anatomy campaigns).

``client(workers, scheduler)`` is a context manager: with ``scheduler`` (an address such as
``tcp://host:8786``) it connects to that existing cluster, else it starts a ``LocalCluster`` of
``workers`` single-threaded processes on loopback. An address that answers nothing within
``timeout_s`` is an :class:`~lvenv.validation.InputError` naming it.

Interrupts. A terminal's Ctrl-C sends SIGINT to the whole process group, the local workers
included, which then died with a traceback each. The local workers start with SIGINT ignored
(they inherit it, :func:`_interrupts_ignored`), so this process alone handles it: it raises
``KeyboardInterrupt``, the ``with`` block closes the cluster, and the workers are shut down
with it. A worker's own subprocess that must stop on Ctrl-C resets SIGINT itself (the FE solve
of ``python -m fe_oracle.solve``). A local worker closed amid a task logs a warning that the
task "ended with CancelledError" (the worker's state machine: it happens only in
``Worker.close``); the local workers drop that one record (:func:`quiet_close`, run on each
as the cluster starts), so that an interrupted command ends with its own message alone.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import threading
from collections.abc import Iterator

from lvenv.validation import InputError, integer

__all__ = ["client", "default_workers", "quiet_close"]


def default_workers() -> int:
    """Worker processes of a default ``LocalCluster``: one per core this process may use."""
    return max(1, len(os.sched_getaffinity(0)))


def _not_a_cancelled_close(record: logging.LogRecord) -> bool:
    return not record.getMessage().endswith("ended with CancelledError")


def quiet_close() -> None:
    """In a Dask worker: its state machine drops the warning that a task "ended with
    CancelledError" as the worker closes amid it (module docstring); its other records are kept."""
    log = logging.getLogger("distributed.worker.state_machine")
    if _not_a_cancelled_close not in log.filters:
        log.addFilter(_not_a_cancelled_close)


@contextlib.contextmanager
def _interrupts_ignored() -> Iterator[None]:
    """SIGINT ignored in this process meanwhile (the main thread only can change it), so that
    the processes it starts inherit it ignored (module docstring)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


@contextlib.contextmanager
def client(workers: int | None = None, scheduler: str | None = None, *, timeout_s: float = 10.0) -> Iterator:
    """A ``dask.distributed.Client`` on a fresh ``LocalCluster`` (``workers`` processes, default
    :func:`default_workers`) or on the cluster at ``scheduler``; closed on exit."""
    from dask.distributed import Client, LocalCluster

    if scheduler is not None:
        if not isinstance(scheduler, str) or "://" not in scheduler:
            raise InputError(f"scheduler = {scheduler!r} is not a Dask scheduler address; give one such as tcp://127.0.0.1:8786")
        try:
            handle = Client(scheduler, timeout=timeout_s)
        except (OSError, TimeoutError) as err:
            raise InputError(f"no Dask scheduler answers at scheduler = {scheduler!r} within {timeout_s:g} s ({type(err).__name__}: {err})") from None
        with contextlib.closing(handle):
            yield handle
        return
    workers = default_workers() if workers is None else integer("workers", workers, 1)
    with _interrupts_ignored():
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0")
    with cluster, Client(cluster) as handle:
        handle.run(quiet_close)
        yield handle
