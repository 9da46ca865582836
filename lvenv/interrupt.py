"""Ctrl-C that ends a command within a second or two, even inside a long compiled computation.

Python runs its SIGINT handler only between bytecodes of the main thread. While that thread waits
on a compiled JAX program (a 10 000-beat simulation), a PETSc solve or a Dask cluster, the
``KeyboardInterrupt`` comes late or never, and the interpreter's shutdown then waits for the
computation still running in XLA's threads. :func:`watchdog` therefore also listens in a thread:
the C-level handler writes the signal to a wake-up socket (:func:`signal.set_wakeup_fd`) even
while the main thread is busy, and if the process has not ended ``grace_s`` after the first
Ctrl-C, the thread prints ``aborted`` and ends the process with :func:`os._exit`; if the main
thread does get the ``KeyboardInterrupt`` in time, the process ends with :func:`os._exit` as it
leaves the block.

Checkpoints stay whole because each is written so that a process ended between any two
instructions leaves it usable: archives and JSON records are replaced atomically
(:mod:`lvenv.archive`), cohort rows are flushed and fsynced one at a time and a torn last row is
dropped on resume (:mod:`optim.cohort`).
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import sys
import threading
from collections.abc import Iterator

__all__ = ["watchdog", "GRACE_S"]

#: Seconds between the first Ctrl-C and the forced exit, for the ordinary ``KeyboardInterrupt`` to finish.
GRACE_S = 1.0


@contextlib.contextmanager
def watchdog(exit_code: int, message: str = "aborted", grace_s: float = GRACE_S) -> Iterator[None]:
    """Within the block, a Ctrl-C ends the process: with ``exit_code`` and ``message`` on stderr
    if it is still busy ``grace_s`` seconds later, else with ``exit_code`` as the block is left
    (so that the interpreter's shutdown does not wait for a computation still running in XLA's
    threads). Main thread only; elsewhere a no-op."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    receiver, sender = socket.socketpair()
    sender.setblocking(False)
    previous_fd = signal.set_wakeup_fd(sender.fileno(), warn_on_full_buffer=False)
    interrupted, left = threading.Event(), threading.Event()

    def watch() -> None:
        while (received := receiver.recv(1)) != bytes([signal.SIGINT]):
            if not received:  # the block was left: the other end is closed
                return
        interrupted.set()
        if not left.wait(grace_s):
            sys.stderr.write(f"lvenv: {message}\n")
            sys.stderr.flush()
            os._exit(exit_code)

    thread = threading.Thread(target=watch, name="lvenv-interrupt-watchdog", daemon=True)
    thread.start()
    try:
        yield
    finally:
        left.set()
        signal.set_wakeup_fd(previous_fd)
        sender.close()
        thread.join(0.1)
        if interrupted.is_set():
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(exit_code)
        receiver.close()
