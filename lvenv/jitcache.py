"""JAX's persistent compilation cache, so that a new process does not recompile the LO heart.

A fit compiles the env's step, which also resets (about 10 s on a 2-core CPU), in every new
process. With the cache on, XLA's compiled programs are stored on disk, keyed by the program,
the JAX and XLA versions and the device, and a later process with the same program loads them
instead (`scripts/bench_cold_start.py` measures the times; the benchmarks page shows them).
Tracing still runs in every process.

Directory: ``$LVENV_JIT_CACHE`` if set, else ``$XDG_CACHE_HOME/lvenv/jax`` (default
``~/.cache/lvenv/jax``). ``LVENV_JIT_CACHE=off`` turns it off. The ``lvenv`` CLI calls
:func:`enable` unless given ``--no-jit-cache``; library users call it themselves. Entries are
safe to delete at any time (the cache only costs a recompilation). A directory that cannot be
made or written is never fatal: :func:`enable` warns (:class:`JitCacheWarning`) and the process
runs without the cache.
"""

from __future__ import annotations

import os
import tempfile
import warnings
from pathlib import Path

import jax

__all__ = ["default_dir", "enable", "OFF", "JitCacheWarning"]

OFF = "off"
#: Programs compiling faster than this are not worth a disk entry (s).
MIN_COMPILE_TIME_S = 0.5


class JitCacheWarning(UserWarning):
    """The cache directory is unusable; the process runs without the persistent cache."""


def default_dir() -> Path | None:
    """The cache directory (module docstring), or None when ``LVENV_JIT_CACHE=off``."""
    chosen = os.environ.get("LVENV_JIT_CACHE")
    if chosen is not None:
        return None if chosen.strip().lower() == OFF else Path(chosen).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "lvenv" / "jax"


def enable(directory: str | os.PathLike[str] | None = None) -> Path | None:
    """Turn on the persistent cache in ``directory`` (default :func:`default_dir`); returns the
    directory used, or None when the cache is off or unusable (then with a :class:`JitCacheWarning`).
    Call it before the first compilation."""
    path = Path(directory).expanduser() if directory is not None else default_dir()
    if path is None:
        return None
    try:
        path.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=path):
            pass
    except OSError as err:
        warnings.warn(f"the JAX compilation cache {str(path)!r} is unusable ({err.strerror or err}); running without it "
                      f"(set LVENV_JIT_CACHE to a writable folder, or to '{OFF}')", JitCacheWarning, stacklevel=2)
        return None
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_TIME_S)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path
