"""The persistent JAX compilation cache the command line uses, so a second run skips compiling.

`jaxps` compiles the same few programs on every run (one per image size and option set); with
the cache they are read back from disk instead (about 1 s less per run at 1 MP, see
docs/speed.md). The folder is `$JAXPS_CACHE_DIR`, else `$XDG_CACHE_HOME/jaxps/xla`, else
`~/.cache/jaxps/xla`; `JAXPS_CACHE_DIR=off` (or empty) disables it. A cache folder the user
already gave JAX (`JAX_COMPILATION_CACHE_DIR`) is left as it is.

The same folder holds, under `executables/`, jaxps's own store of its hot programs
(`core._store`): those are loaded without being traced and lowered again.
"""

from __future__ import annotations

import os
import pathlib

__all__ = ["enable_compilation_cache"]

_OFF = ("", "0", "off", "none", "false")


def enable_compilation_cache(path: str | os.PathLike | None = None) -> pathlib.Path | None:
    """Turn on JAX's persistent compilation cache in `path` (default: see the module docs).

    Call before the first jitted call of the process; every compiled program is then kept,
    however quick its compile. Also usable from Python scripts that run many short jobs.
    jaxps's hot programs (the L2 solve and its flag pass, FC and DCT integration, the
    parametric BRDF fit) are also kept whole in `path / "executables"`, so that a new process
    loads them without tracing them again (`core._store`).

    **Returns:** the cache folder, or None when disabled (`JAXPS_CACHE_DIR=off`) or when JAX
    already has a cache folder from its own settings.
    """
    import jax

    if jax.config.jax_compilation_cache_dir:
        return None
    if path is None:
        path = os.environ.get("JAXPS_CACHE_DIR")
        if path is None:
            base = os.environ.get("XDG_CACHE_HOME") or pathlib.Path.home() / ".cache"
            path = pathlib.Path(base) / "jaxps" / "xla"
        elif path.strip().lower() in _OFF:
            return None
    path = pathlib.Path(path).expanduser()
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None  # a read-only home: run without the cache rather than fail
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)
    from ..core._store import use_store

    use_store(path / "executables")
    return path
