"""Quality checks over every frame of both Yale B subjects and the psm objects.

Run: `PYTHONPATH=src python benchmarks/quality_real.py` -> benchmarks/results/quality_real.json
"""

from __future__ import annotations

import json
import os
import pathlib

import cv2
import numpy as np

import jaxps

ROOT = pathlib.Path(__file__).resolve().parents[1]
DATA = pathlib.Path(os.environ.get("JAXPS_DATA", ROOT.parent / "shared" / "data"))


def main():
    out = {}
    for subject in ("yaleB01", "yaleB02"):
        paths = sorted((DATA / "yaleb" / subject).glob("*.pgm"))
        files = {p.name: jaxps.check_file(p) for p in paths}
        frames = np.stack([cv2.imread(str(p), cv2.IMREAD_UNCHANGED) for p in paths])
        report = jaxps.check_frames(frames.astype(np.float32) / 255, names=[p.name for p in paths])
        out[subject] = {"frames": len(paths),
                        "file_problems": {k: v for k, v in files.items() if v},
                        "flagged": {f.name: list(f.reasons) for f in report.flagged}}
        print(subject, report.summary())
    for obj in ("chrome", "cat", "owl"):
        folder = DATA / "psm" / obj
        paths = [folder / f"{obj}.{i}.png" for i in range(12)]
        frames = np.stack([cv2.cvtColor(cv2.imread(str(p), cv2.IMREAD_UNCHANGED),
                                        cv2.COLOR_BGR2RGB) for p in paths])
        mask = cv2.imread(str(folder / f"{obj}.mask.png"), cv2.IMREAD_GRAYSCALE) > 127
        report = jaxps.check_frames(frames.astype(np.float32) / 255,
                                    names=[p.name for p in paths], mask=mask)
        out[obj] = {"frames": 12, "flagged": {f.name: list(f.reasons) for f in report.flagged}}
        print(obj, report.summary())
    (ROOT / "benchmarks" / "results" / "quality_real.json").write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    import argparse

    argparse.ArgumentParser(description=__doc__).parse_args()  # --help before any work
    main()
