import os
import pathlib

import jax
import pytest

# Catch silent broadcasting and dtype promotion in the library (STYLE.md).
jax.config.update("jax_numpy_rank_promotion", "raise")
jax.config.update("jax_numpy_dtype_promotion", "strict")

ROOT = pathlib.Path(__file__).resolve().parents[1]

# The command line turns on a persistent compilation cache in the user's cache folder; tests
# that call `jaxps.cli.main` in this process leave it off (test_cli.py tests it on its own).
os.environ.setdefault("JAXPS_CACHE_DIR", "off")


def data_dir() -> pathlib.Path:
    """The shared real captures: $JAXPS_DATA, else ../shared/data beside the checkout."""
    return pathlib.Path(os.environ.get("JAXPS_DATA", ROOT.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def data():
    path = data_dir()
    if not (path / "README.md").is_file():
        pytest.skip(f"shared data not found at {path} (set JAXPS_DATA)")
    return path
