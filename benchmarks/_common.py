"""Helpers shared by the benchmark scripts: timing, data paths, JSON output."""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import platform
import statistics
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"


def arguments(doc: str | None, quick: bool = False, configure=None,
              argv=None) -> argparse.Namespace:
    """Parse a benchmark script's command line, so that `--help` prints its docstring and an
    unknown option stops it, before any work or any write to `results/`.

    `quick`: the script takes `--quick` (a small smoke run); `configure(parser)` adds the
    script's own options."""
    parser = argparse.ArgumentParser(description=doc,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    if quick:
        parser.add_argument("--quick", action="store_true", help="small inputs, few repeats")
    if configure is not None:
        configure(parser)
    return parser.parse_args(argv)


def data_dir() -> pathlib.Path:
    """The shared real captures: $JAXPS_DATA, else ../shared/data beside the checkout."""
    return pathlib.Path(os.environ.get("JAXPS_DATA", ROOT.parent / "shared" / "data"))


SHARED_SUBJECTS = ("yaleB01", "yaleB02", "yaleB03", "yaleB04", "yaleB05")


def yale_subjects() -> list[str]:
    """The Yale B subjects the face benchmarks score by default: every `yaleB*` folder in
    `data_dir() / "yaleb"`, sorted, so that subjects added beside the five shared ones (or a
    `$JAXPS_DATA` holding others) are scored without naming them. The five shared names when
    there is no such folder (each script then says that the data is missing)."""
    found = sorted(p.name for p in (data_dir() / "yaleb").glob("yaleB*") if p.is_dir())
    return found or list(SHARED_SUBJECTS)


def clean_frames(images, angles, label: str = ""):
    """`(K,)` bool: the Yale B frames that pass `jaxps.check_frames` (two of yaleB02's are
    interlace-combed). Only the frames within 60 deg of the view axis (the ones the benchmarks
    use) are checked; the rest count as clean. The report is printed.

    - `images`: `(K, H, W)` ambient-subtracted frames in [0, 1] (clipped here).
    - `angles`: `K` (azimuth, elevation) pairs in degrees.
    """
    import numpy as np

    import jaxps

    angles = np.asarray(angles, float)
    lights = jaxps.lights_from_angles(angles[:, 0], angles[:, 1])
    used = np.flatnonzero(lights[:, 2] >= np.cos(np.radians(60)) - 1e-6)
    report = jaxps.check_frames(np.clip(np.asarray(images)[used], 0, 1),
                                names=[f"{a:+.0f},{e:+.0f}" for a, e in angles[used]])
    for line in report.summary().splitlines():
        print(f"{label}: {line}" if label else line, flush=True)
    clean = np.ones(len(angles), bool)
    clean[used] = report.keep
    return clean


def block(x):
    """Wait for every JAX array in `x` (a pytree) to be computed."""
    import jax

    return jax.block_until_ready(x)


def _calls(fn, repeats: int):
    """`(last output, first call s, [later call s, ...])` of `fn()`, each call waited for."""
    t0 = time.perf_counter()
    out = block(fn())
    first = time.perf_counter() - t0
    runs = []
    for _ in range(max(repeats, 1)):
        t0 = time.perf_counter()
        out = block(fn())
        runs.append(time.perf_counter() - t0)
    return out, first, runs


def timed(fn, *args, repeats: int = 3, **kwargs):
    """Time `fn`: the first call (compile + run) apart from the best of `repeats` later calls.

    **Returns:** `(result, first_call_s, run_s)`; `compile_s` is about `first_call_s - run_s`.
    """
    out, first, runs = _calls(lambda: fn(*args, **kwargs), repeats)
    return out, first, min(runs)


def time_calls(fn, repeats: int = 3) -> dict:
    """Time `fn()`: the first call (compile + run) apart from `repeats` later calls.

    **Returns:** `{"first_call_s", "run_s_min", "run_s_median"}`.
    """
    _, first, runs = _calls(fn, repeats)
    return {"first_call_s": first, "run_s_min": min(runs),
            "run_s_median": statistics.median(runs)}


def page_faults(fn) -> int:
    """Minor page faults of one more call of `fn()` (waited for): first writes to 4 KiB pages
    that the allocator has just taken from the kernel. glibc maps allocations of 32 MiB and
    more afresh every time, so large outputs pay one per page on every call."""
    import resource

    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    block(fn())
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before


def interleaved(cases: dict, rounds: int, faults: dict | None = None):
    """Time the zero-argument callables `cases` (each call waited for) in `rounds` interleaved
    rounds, so that the load of a shared machine hits them alike.

    **Returns:** `(first_call_s, seconds)`: `{name: s}` of each first call (compile + run), and
    `{name: [s, ...]}` of the later calls, one per round. `faults`: a dict to fill with
    `{name: [minor page faults, ...]}` of the same later calls.
    """
    import resource

    first = {}
    for name, fn in cases.items():
        t0 = time.perf_counter()
        block(fn())
        first[name] = time.perf_counter() - t0
    seconds = {name: [] for name in cases}
    counts = {name: [] for name in cases}
    for _ in range(rounds):
        for name, fn in cases.items():
            before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
            t0 = time.perf_counter()
            block(fn())
            seconds[name].append(time.perf_counter() - t0)
            counts[name].append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
    if faults is not None:
        faults.update(counts)
    return first, seconds


def environment() -> dict:
    """What the figures were measured on (thread settings included)."""
    import jax
    import numpy as np

    return {
        "python": platform.python_version(),
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
        "jax": jax.__version__,
        "jax_backend": jax.default_backend(),
        "numpy": np.__version__,
        "OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS"),
        "XLA_FLAGS": os.environ.get("XLA_FLAGS"),
        # the allocator settings that change page faults (docs/speed.md), where set
        "allocator": {k: v for k, v in os.environ.items()
                      if k == "GLIBC_TUNABLES" or k.startswith("MALLOC_")},
        "transparent_hugepage": _thp_mode(),
        "cpu": cpu_model(),
        "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }


def cpu_model() -> str | None:
    """The CPU's model name, family and model, and its widest vector extension (the machines
    these benchmarks run on change from day to day, and numpy's BLAS and XLA pick their
    kernels by them), if Linux."""
    try:
        text = pathlib.Path("/proc/cpuinfo").read_text()
    except OSError:
        return None
    info = dict(line.split(":", 1) for line in text.split("\n\n")[0].splitlines()
                if ":" in line)
    info = {k.strip(): v.strip() for k, v in info.items()}
    flags = info.get("flags", "").split()
    vector = next((f for f in ("avx512f", "avx2", "avx") if f in flags), "none")
    return (f"{info.get('model name', '?')} (family {info.get('cpu family', '?')}, "
            f"model {info.get('model', '?')}), {vector}")


def _thp_mode() -> str | None:
    """The kernel's transparent-huge-page mode (`always`, `madvise` or `never`), if Linux."""
    try:
        text = pathlib.Path("/sys/kernel/mm/transparent_hugepage/enabled").read_text()
    except OSError:
        return None
    return text.split("[")[1].split("]")[0] if "[" in text else text.strip()


def write_json(name: str, payload: dict) -> pathlib.Path:
    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / f"{name}.json"
    path.write_text(json.dumps(payload, indent=2, sort_keys=False, default=float) + "\n")
    return path


def module_at(rev: str, path: str, folder: pathlib.Path):
    """The jaxps module at `path` (e.g. `"src/jaxps/lights/_near.py"`) as it was at git revision
    `rev`, loaded next to the current one as `<its package>.<its name>_before` (its source
    written to `folder`; its relative imports reach the current tree's modules), so that a
    benchmark can time both in one process."""
    import importlib.util
    import subprocess
    import sys

    source = subprocess.run(["git", "show", f"{rev}:{path}"], cwd=ROOT, check=True,
                            capture_output=True, text=True).stdout
    parts = pathlib.PurePosixPath(path).with_suffix("").parts[1:]  # past "src"
    name = ".".join(parts[:-1]) + f".{parts[-1]}_before"
    file = folder / f"{parts[-1]}_before.py"
    file.write_text(source)
    spec = importlib.util.spec_from_file_location(name, file)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module
