"""Compiled programs kept on disk, so that a new process skips tracing and lowering too.

JAX's persistent compilation cache (`jaxps.cli.enable_compilation_cache`) finds a program by
its lowered HLO, so every new process still traces and lowers each program before it can
look it up. That was most of a warm `jaxps reconstruct`'s photometric-stereo and integration
stages: 0.18 and 0.07 s at 1 MP, against 0.013 and 0.02 s for the same calls repeated in one
process (docs/speed.md, "The command line").

This store finds an executable by what tracing depends on instead, then loads it with
`jax.experimental.serialize_executable`:

- the program (its module and name), its static arguments and its compile options;
- the tree structure, shapes, dtypes and weak types of its arguments;
- a fingerprint of everything else that can change the program: the source of every jaxps
  module, the versions of JAX, jaxlib and numpy, JAX's settings, `XLA_FLAGS`, and the CPU.

It is on only after `use_store(folder)`, which `enable_compilation_cache` calls (so for the
command line, and for scripts that turn the cache on), and only for top-level calls on the
CPU of the programs that go through `call`. Programs with custom calls other than jaxlib's
LAPACK kernels are never stored, and anything that fails (a file from another version, a
program that does not serialize) falls back to the plain jitted call.

The files are read back with `pickle`, so the folder must be as private as the code (the
default is in the user's own cache directory; the files are written readable by their owner
only). Nothing is evicted: each new jaxps version or image size adds a few files of tens of
KB, and deleting the folder is always safe.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import pathlib
import pickle
import platform
import re
import tempfile

from ._host import cpu_top_level

__all__ = ["active", "call", "stats", "use_store"]

_folder: pathlib.Path | None = None
_executables: dict = {}  # key -> executable, or None: this key takes the plain jit
_fingerprint: str | None = None
_stats = {"loaded": 0, "compiled": 0, "plain": 0}
_LOG_SETTINGS = ("jax_log_compiles", "jax_logging_level", "jax_debug_log_modules",
                 "jax_log_checkpoint_residuals")


def use_store(folder: str | os.PathLike | None) -> None:
    """Keep compiled programs in `folder` (created if needed), or stop with None."""
    global _folder
    _folder = None if folder is None else pathlib.Path(folder)
    if _folder is not None:
        _folder.mkdir(parents=True, exist_ok=True)


def active() -> bool:
    """Whether the store is on (`use_store` with a folder): a process that loads its programs
    from disk, such as a `jaxps` command."""
    return _folder is not None


def stats() -> dict:
    """How many calls of this process loaded an executable from the store, compiled and
    stored one, or found a program the store cannot keep (it then runs the plain jit; each
    such program counts once). Calls with the store off count nowhere."""
    return dict(_stats)


def call(program, *args, **static):
    """`program(*args, **static)`, from the store where it holds the executable.

    `program`: a `jax.jit` function or a `core._host.CpuTuned` one (anything else is called
    as it is); `args` its dynamic arguments, positional; `static` its static arguments, by
    name. Nothing it takes may be donated: a failed first run of a loaded executable is run
    again with the plain jit.
    """
    jitted, options = _jit_and_options(program)
    if _folder is None or not hasattr(jitted, "lower") or not cpu_top_level(args, static):
        return program(*args, **static)
    try:
        key = _key(jitted, options, args, static)
    except TypeError:  # an argument that is not an array: no key
        return program(*args, **static)
    if key not in _executables:
        loaded = _load_and_run(key, args)
        if loaded is not None:
            _executables[key], result = loaded
            return result
        _executables[key] = _compile(jitted, options, args, static, key)
    executable = _executables[key]
    return program(*args, **static) if executable is None else executable(*args)


def _jit_and_options(program):
    if hasattr(program, "plain"):  # CpuTuned: its options, unless this XLA rejected them
        return program.plain, program.options if program.known else None
    return program, None


def _key(jitted, options, args, static) -> str:
    import jax

    leaves, tree = jax.tree.flatten(args)
    avals = [repr(jax.api_util.shaped_abstractify(leaf)) for leaf in leaves]
    fun = getattr(jitted, "__wrapped__", jitted)
    parts = [_code_fingerprint(), f"{fun.__module__}.{fun.__qualname__}", repr(options),
             repr(sorted(static.items())), str(tree), *avals]
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()


def _code_fingerprint() -> str:
    """Everything outside a call that can change what it compiles to (once per process)."""
    global _fingerprint
    if _fingerprint is None:
        import jax
        import jaxlib
        import numpy as np

        digest = hashlib.sha256()
        package = pathlib.Path(__file__).resolve().parents[1]
        for path in sorted(package.rglob("*.py")):
            digest.update(str(path.relative_to(package)).encode())
            digest.update(path.read_bytes())
        # every JAX setting but those of caches and logs, which do not change a program
        config = sorted((k, repr(v)) for k, v in jax.config.values.items()
                        if "cache" not in k and k not in _LOG_SETTINGS)
        for part in (jax.__version__, jaxlib.__version__, np.__version__, repr(config),
                     os.environ.get("XLA_FLAGS", ""), platform.machine(), _cpu()):
            digest.update(part.encode())
        _fingerprint = digest.hexdigest()
    return _fingerprint


def _cpu() -> str:
    """The CPU's model and features (machine code compiled for one CPU may not run on
    another, as with a cache folder shared between machines)."""
    try:
        with open("/proc/cpuinfo") as f:
            lines = [ln for ln in f if ln.startswith(("model name", "flags"))]
        return "".join(sorted(set(lines)))
    except OSError:
        return platform.processor()


def _path(key: str) -> pathlib.Path:
    return _folder / f"{key}.exe"


def _load_and_run(key: str, args):
    """The stored executable for `key` and its result on `args`, or None. Its first run is
    waited for, so that a broken file fails here (and is removed), not in the caller."""
    executable = _load(key)
    if executable is None:
        return None
    try:
        import jax

        result = jax.block_until_ready(executable(*args))
    except Exception:  # noqa: BLE001 - whatever a loaded executable raises, recompile
        _remove(key)
        return None
    _stats["loaded"] += 1
    return executable, result


def _load(key: str):
    path = _path(key)
    if not path.is_file():
        return None
    try:
        from jax.experimental import serialize_executable

        with open(path, "rb") as f:
            payload, in_tree, out_tree, lapack = pickle.load(f)
        if lapack:
            _initialize_lapack()
        return serialize_executable.deserialize_and_load(payload, in_tree, out_tree)
    except Exception:  # noqa: BLE001 - another jaxlib's file, a torn write: compile afresh
        _remove(key)
        return None


def _compile(jitted, options, args, static, key):
    """Trace, lower and compile `jitted` for these arguments, then store the executable;
    None (the plain jit from then on) if any of it fails."""
    import jax

    try:
        lowered = jitted.lower(*args, **static)
        with _without_jax_cache():
            executable = lowered.compile(options) if options else lowered.compile()
        targets = set(re.findall(r'custom_call_target="([^"]*)"', executable.as_text()))
        if any(not t.startswith("lapack_") for t in targets):
            # a custom call whose set-up in a process that only loads it is unknown
            _stats["plain"] += 1
            return None
        from jax.experimental import serialize_executable

        blob = pickle.dumps((*serialize_executable.serialize(executable), bool(targets)))
        _, in_tree, out_tree, _ = pickle.loads(blob)
        for tree in (in_tree, out_tree):  # e.g. an equinox enumeration item fails here once
            jax.tree.unflatten(tree, [0] * tree.num_leaves)  # pickled: keep the plain jit
    except Exception:  # noqa: BLE001 - a program that does not lower or serialize: plain jit
        _stats["plain"] += 1
        return None
    try:  # written whole, then renamed: a reader never sees half a file
        with tempfile.NamedTemporaryFile(dir=_folder, delete=False, suffix=".tmp") as f:
            f.write(blob)
        os.replace(f.name, _path(key))
    except OSError:
        pass  # a read-only folder: this process keeps the executable in memory
    _stats["compiled"] += 1
    return executable


@contextlib.contextmanager
def _without_jax_cache():
    """Compiles inside neither read nor write JAX's persistent cache.

    An executable read back from that cache serializes without its machine code, and fails
    to run once loaded. JAX decides once per process whether its cache is in use
    (`compilation_cache.is_cache_used`), so switching `jax_enable_compilation_cache` off for a
    moment would either do nothing or keep the cache off for the rest of the process; this
    sets that decision for the compiles inside and puts it back after. JAX internals: with a
    JAX that has no such state this raises, and `_compile` keeps the plain jit.
    """
    from jax._src import compilation_cache as cache

    with cache._cache_initialized_mutex:
        saved = cache._cache_checked, cache._cache_used
        cache._cache_checked, cache._cache_used = True, False
    try:
        yield
    finally:
        with cache._cache_initialized_mutex:
            cache._cache_checked, cache._cache_used = saved


def _initialize_lapack() -> None:
    """Set jaxlib's LAPACK function pointers, as lowering a LAPACK call does. A process that
    only loads an executable with such a call lowers none, and without this the call jumps
    to a null pointer (a crash, not an error to catch). JAX internals: with a JAX that has no
    such function this raises, and `_load` compiles afresh."""
    from jax._src.lax.linalg import initialize_lapack

    initialize_lapack()


def _remove(key: str) -> None:
    try:
        _path(key).unlink()
    except OSError:
        pass
