"""Ctrl-C ends a command within a second or two, even while the compiled model runs."""

import contextlib
import os
import signal
import subprocess
import sys
import time

import pytest

#: Compiles the 10 000-beat program on a member that fails at once (nonfinite start), says so,
#: then runs ``lvenv simulate`` with the same program: 10 000 beats, minutes of work.
SCRIPT = """
import sys
import numpy as np
import lvenv
from lvenv import cli, presets
lvenv.simulate(presets.normal(), beats=10000, steps_per_beat=1000, traces=False, initial_state=np.full(9, np.nan))
print("running", flush=True)
sys.exit(cli.main(["--no-jit-cache", "simulate", "--beats", "10000", "--json"]))
"""


def test_ctrl_c_stops_a_long_simulation_within_two_seconds():
    # a terminal's Ctrl-C: SIGINT at its default disposition (a background job inherits it ignored)
    child = subprocess.Popen([sys.executable, "-c", SCRIPT], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                             env={**os.environ, "LVENV_JIT_CACHE": "off"}, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        assert child.stdout.readline() == "running\n", child.stderr.read()
        time.sleep(2.0)  # inside the compiled 10 000-beat loop
        sent = time.perf_counter()
        child.send_signal(signal.SIGINT)
        _, err = child.communicate(timeout=30)
        took = time.perf_counter() - sent
    finally:
        child.kill()
    assert took < 2.0, f"the process ran on for {took:.1f} s after Ctrl-C"
    assert child.returncode == 1 and "lvenv: aborted" in err and "Traceback" not in err


@pytest.mark.parametrize("finished", [False, pytest.param(True, marks=pytest.mark.slow)], ids=["amid-the-first-anatomies", "after-one-anatomy"])
def test_ctrl_c_on_a_campaign_with_local_workers_prints_no_traceback_and_keeps_finished_anatomies(tmp_path, finished):
    """A terminal's Ctrl-C reaches the whole process group: the command, its Dask workers and
    their FE solves. Before, each worker died with a traceback; now the command alone handles it,
    the anatomies finished so far are kept, the interrupted ones stay pending, no process is left.
    The default run interrupts once the workers' first FE run is cached (nothing finished yet, a
    minute sooner); the slow one once an anatomy is accepted."""
    from optim import campaign

    folder, cache = tmp_path / "campaign", tmp_path / "cache"

    def ready() -> bool:
        if not finished:
            return any(cache.glob("*.npz"))
        index = folder / "anatomies.csv"
        return index.exists() and any(r["status"] == "accepted" for r in campaign.read_index(folder))

    command = [sys.executable, "-m", "lvenv.cli", "--no-jit-cache", "campaign", "run", str(folder), "--n", "6", "--held-out", "0",
               "--backend", "multielement", "--n-elements", "4", "--budget", "16", "--workers", "2", "--cache-dir", str(cache)]
    child = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                             env={**os.environ, "LVENV_JIT_CACHE": "off"}, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        deadline = time.monotonic() + 240
        while time.monotonic() < deadline and child.poll() is None and not ready():
            time.sleep(0.5)
        assert child.poll() is None, "the campaign ended before it could be interrupted"
        os.killpg(child.pid, signal.SIGINT)  # what a terminal does: the whole foreground group
        _, err = child.communicate(timeout=60)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(child.pid, signal.SIGKILL)
    assert child.returncode == 1 and "lvenv: aborted" in err and "Traceback" not in err, err
    assert "CancelledError" not in err, "the workers closed amid their tasks say nothing (optim.cluster.quiet_close)"
    statuses = [r["status"] for r in campaign.read_index(folder)]
    assert ("accepted" in statuses) == finished and "pending" in statuses and set(statuses) <= {"accepted", "pending"}, statuses
    left = time.monotonic() + 20
    while time.monotonic() < left:  # the workers follow their parent out within seconds
        try:
            os.killpg(child.pid, 0)
        except ProcessLookupError:
            break
        time.sleep(0.5)
    with pytest.raises(ProcessLookupError):
        os.killpg(child.pid, 0)  # nothing of the group is left running
