import gc
import os
import pathlib

import jax
import pytest

import jaxps

# Catch silent broadcasting and dtype promotion in the library (STYLE.md).
jax.config.update("jax_numpy_rank_promotion", "raise")
jax.config.update("jax_numpy_dtype_promotion", "strict")

ROOT = pathlib.Path(__file__).resolve().parents[1]

# The command line turns on a persistent compilation cache in the user's cache folder; tests
# that call `jaxps.cli.main` in this process leave it off (test_cli.py tests it on its own).
os.environ.setdefault("JAXPS_CACHE_DIR", "off")


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """Drop every compiled program (and the batch outputs kept for reuse) after each test file.

    Each XLA executable keeps memory mappings for its machine code, so one process running the
    whole suite piled them up towards the kernel's limit per process (`vm.max_map_count`,
    65530 here); past it, XLA crashed with a segmentation fault while compiling a program
    (CI, 2026-12-05, in test_robust.py). Programs a later file needs are compiled again."""
    yield
    jax.clear_caches()
    jaxps.release_batch_outputs()
    gc.collect()


def data_dir() -> pathlib.Path:
    """The shared real captures: $JAXPS_DATA, else ../shared/data beside the checkout."""
    return pathlib.Path(os.environ.get("JAXPS_DATA", ROOT.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def data():
    path = data_dir()
    if not (path / "README.md").is_file():
        pytest.skip(f"shared data not found at {path} (set JAXPS_DATA)")
    return path
