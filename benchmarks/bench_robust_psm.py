"""Robust vs L2 on the real psm objects (cat, owl), against a 12-light robust reference.

Writes benchmarks/results/robust_psm.json. Run:
    OPENBLAS_NUM_THREADS=1 PYTHONPATH=src python benchmarks/bench_robust_psm.py
Images: psm PNGs decoded from sRGB to linear (`jaxps.load_psm`), every 2nd pixel, lights.txt.
Reference: `method="sbl"` on all 12 clean images (also "irls" and "l2" references, to show the
ranking does not come from the reference's own method).
(a) corrupted: per pixel, with probability 0.3 one random sample is set to 0 (a shadow) and with
    probability 0.3 another is raised by 0.4 (a highlight); every method solves all 12.
(b) subsets: 4 random K-light subsets (K = 5, 6, 8) of the clean images.
Errors: mean angular error (deg) over the reference's OK object pixels (failed pixels count with
the default normal).
"""

import json
import os
import pathlib

import numpy as np

import jaxps
from jaxps.evaluate import angular_stats

OUT = pathlib.Path(__file__).resolve().parent / "results"
DATA = pathlib.Path(os.environ.get("JAXPS_DATA", pathlib.Path(__file__).resolve().parents[2]
                                   / "shared" / "data"))
METHODS = ("l2", "barsky", "irls", "sbl")


def corrupt(images, rng):
    k, h, w, _ = images.shape
    rr, cc = np.indices((h, w))
    out = images.copy()
    js = rng.integers(0, k, (h, w))
    sel = rng.random((h, w)) < 0.3
    out[js[sel], rr[sel], cc[sel]] = 0
    jb = (js + rng.integers(1, k, (h, w))) % k
    sel = rng.random((h, w)) < 0.3
    out[jb[sel], rr[sel], cc[sel]] = np.minimum(out[jb[sel], rr[sel], cc[sel]] + 0.4, 1)
    return out


def main():
    import argparse

    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="every 4th pixel")
    step = 4 if ap.parse_args().quick else 2
    lights = jaxps.load_lights(DATA / "psm" / "lights.txt")
    doc = {"OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS"), "pixel_step": step,
           "objects": {}}
    for obj in ("cat", "owl"):
        images, mask = jaxps.load_psm(DATA / "psm" / obj)
        images, mask = images[:, ::step, ::step], mask[::step, ::step] > 0.5
        rng = np.random.default_rng(0)
        refs = {m: jaxps.photometric_stereo(images, lights, mask=mask, method=m)
                for m in ("sbl", "irls", "l2")}
        cor = corrupt(images, rng)
        sols = {m: jaxps.photometric_stereo(cor, lights, mask=mask, method=m) for m in METHODS}
        rec = {"corrupted": {}, "subsets": {}}
        for rname, ref in refs.items():
            ok = mask & (np.asarray(ref.status) == 0)
            rec["corrupted"]["ref_" + rname] = {
                m: angular_stats(s.normals, ref.normals, mask=ok)["mean_deg"]
                for m, s in sols.items()}
        for k in (5, 6, 8):
            subs = [np.sort(rng.choice(12, k, replace=False)) for _ in range(4)]
            res = {m: [jaxps.photometric_stereo(images[s], lights[s], mask=mask, method=m)
                       for s in subs] for m in METHODS}
            rec["subsets"][f"K={k}"] = {"subsets": [s.tolist() for s in subs]}
            for rname, ref in refs.items():
                ok = mask & (np.asarray(ref.status) == 0)
                rec["subsets"][f"K={k}"]["ref_" + rname] = {
                    m: float(np.mean([angular_stats(r.normals, ref.normals, mask=ok)["mean_deg"]
                                      for r in rs])) for m, rs in res.items()}
        doc["objects"][obj] = rec
        print(obj, json.dumps(rec, indent=1), flush=True)
    OUT.mkdir(exist_ok=True)
    (OUT / "robust_psm.json").write_text(json.dumps(doc, indent=1))


if __name__ == "__main__":
    main()
