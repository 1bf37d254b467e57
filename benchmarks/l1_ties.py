"""How often the exact L1 fit of `method="l1"` is not unique, and what the choice among the
optimal vertices is worth.

`method="l1"` tries every light triple and keeps the cheapest (docs/robust.md). When the lights
are an axis light with opposite pairs around it (a ring, or the scanner's cross), an outlier in
one light of a pair fits as well as one in its partner, and several triples reach the same
L1 cost: the optimum is an edge of the linear program, not a vertex. This script solves every
triple in float64 numpy on synthetic faces with known normals (Blinn-Phong highlights, cast
shadows, 0.5% noise), counts the pixels whose optimum is shared by two or more triples (costs
within 1e-9 relative), and scores each way of choosing among them: the first in triple order,
the centroid of the tied solutions, the best and the worst tied triple (oracles), and jaxps's
`method="l1"` itself (float32, where rounding decides).

    PYTHONPATH=src python benchmarks/l1_ties.py -> benchmarks/results/l1_ties.json
"""

from __future__ import annotations

import itertools

import jax
import numpy as np

import jaxps
from jaxps.stability import render_corrupted, ring_lights

try:
    from benchmarks._common import arguments, environment, write_json
except ImportError:  # run as a script
    import pathlib
    import sys

    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    from benchmarks._common import arguments, environment, write_json

LIGHT_SETS = {
    "ring: axis + 4 at 45 deg (bench_robust.py)": np.asarray(ring_lights(5, 45.0)),
    "cross: Yale (0,0), (+-25,0), (0,+-20)": jaxps.lights_from_angles([0, 25, -25, 0, 0],
                                                                      [0, 0, 0, 20, -20]),
    "ring: 5 at 45 deg, no axis light": np.asarray(ring_lights(5, 45.0, centre=False)),
}


def angles(b, truth):
    n = b / np.linalg.norm(b, axis=1, keepdims=True)
    return np.degrees(np.arccos(np.clip((n * truth).sum(1), -1, 1)))


def study(lights, h=256, w=320):
    surf = jaxps.synthetic.face_like(h, w)
    scene = render_corrupted(surf, lights, specular=0.6, shininess=100.0, noise=0.005,
                             key=jax.random.key(0))
    images, mask = np.asarray(scene.images), np.asarray(scene.mask)
    truth = np.asarray(scene.normals)[mask]
    g = images[:, mask].T.astype(np.float64)  # (P, K)
    lt = np.asarray(lights, np.float64)
    lt = lt / np.linalg.norm(lt, axis=1, keepdims=True)
    sols, costs = [], []
    for t in itertools.combinations(range(len(lt)), 3):
        sub = lt[list(t)]
        if abs(np.linalg.det(sub)) < 1e-3:  # as ps/_l1.py: the triple does not span 3-D
            continue
        b = np.linalg.solve(sub, g[:, list(t)].T).T
        sols.append(b)
        costs.append(np.abs(g - b @ lt.T).sum(1))
    sols, costs = np.stack(sols), np.stack(costs)  # (T, P, 3), (T, P)
    best = costs.min(0)
    tied = costs <= best * (1 + 1e-9) + 1e-12
    err = np.stack([angles(b, truth) for b in sols])  # (T, P)
    cols = np.arange(g.shape[0])
    centroid = (sols * tied[..., None]).sum(0) / tied.sum(0)[:, None]
    ours = jaxps.photometric_stereo(images, lights, mask=mask, method="l1")
    ours_err = angles(np.asarray(ours.normals)[mask].astype(np.float64), truth)
    stats = {
        "first tied triple": err[np.argmax(tied, 0), cols],
        "centroid of the tied solutions": angles(centroid, truth),
        "best tied triple (oracle)": np.where(tied, err, np.inf).min(0),
        "worst tied triple (oracle)": np.where(tied, err, -np.inf).max(0),
        "jaxps method='l1' (float32)": ours_err,
    }
    return {
        "pixels": int(mask.sum()),
        "fraction_with_tied_optimum": float((tied.sum(0) > 1).mean()),
        "mean_tied_triples": float(tied.sum(0).mean()),
        "mean_deg": {k: float(v.mean()) for k, v in stats.items()},
        "median_deg": {k: float(np.median(v)) for k, v in stats.items()},
    }


def main():
    doc = {"machine": environment(), "shape": [256, 320], "sets": {}}
    for name, lights in LIGHT_SETS.items():
        doc["sets"][name] = r = study(lights)
        print(f"{name}: {100 * r['fraction_with_tied_optimum']:.1f}% of {r['pixels']} pixels "
              f"have a tied optimum ({r['mean_tied_triples']:.2f} triples on average)")
        for k, v in r["mean_deg"].items():
            print(f"    {k:<32} mean {v:6.2f}  median {r['median_deg'][k]:6.2f} deg")
    write_json("l1_ties", doc)


if __name__ == "__main__":
    arguments(__doc__)
    main()
