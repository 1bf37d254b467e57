"""Where the examples find the shared data: $JAXPS_DATA, else ../shared/data beside the repo."""

import os
import pathlib

ROOT = pathlib.Path(__file__).resolve().parents[1]


def data_dir() -> pathlib.Path:
    return pathlib.Path(os.environ.get("JAXPS_DATA", ROOT.parent / "shared" / "data"))
