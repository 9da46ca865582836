"""One oracle run in a process of its own: ``python -m fe_oracle.solve REQUEST``.

``REQUEST`` is a JSON object: ``geometry`` (the `Geometry` fields), ``case`` ("passive" or 1–3),
``backend``, ``options`` (keyword arguments of :func:`fe_oracle.run`) and ``cache_dir`` (None:
the cache's default). The result goes into the oracle's content-hash cache; the process prints
``computed KEY`` or ``cached KEY`` and exits 0, or prints the error on stderr and exits 3. A
campaign (:mod:`optim.campaign`) runs every FE solve this way, with a timeout, so that a crash or
a hang ends this process, not the worker that started it. It imports only ``fe_oracle`` and
``lvenv``, and turns on JAX's persistent compilation cache (:mod:`lvenv.jitcache`) as every
``lvenv`` command does. A Ctrl-C ends it at once (SIGINT at its default disposition, even when
started by a Dask worker that ignores it, :mod:`optim.cluster`): its caller sees it killed by
SIGINT and keeps nothing of it.
"""

from __future__ import annotations

import json
import signal
import sys

from lvenv import jitcache
from lvenv.geometry import Geometry
from lvenv.validation import InputError

from fe_oracle.api import run
from fe_oracle.result import OracleDidNotConverge

__all__ = ["main"]


def main(request_json: str) -> int:
    """Run the request (module docstring); returns the exit code."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    jitcache.enable()
    request = json.loads(request_json)
    try:
        result = run(Geometry(**request["geometry"]), request["case"], request["backend"], cache_dir=request["cache_dir"], progress=False,
                     **request["options"])
    except (OracleDidNotConverge, InputError, RuntimeError) as err:
        print(f"{type(err).__name__}: {err}", file=sys.stderr)
        return 3
    print("cached" if result.from_cache else "computed", result.metadata["key"])
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1]))
