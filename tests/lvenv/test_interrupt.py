"""Ctrl-C ends a command within a second or two, even while the compiled model runs."""

import os
import signal
import subprocess
import sys
import time

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
