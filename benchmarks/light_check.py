"""The figures behind `jaxps.check_lights`: the normals' curl and convexity with the lights
as given, and with the lights file wrong in the ways an operator gets it wrong.

- Each shared Yale B subject's five scanner frames, loaded as `jaxps reconstruct
  --yale-names --ambient` loads them (`load_capture` defaults, no mask), with the lights as
  given; negated in y (image rows for y) and in x; the left and right lamps swapped; the
  four outer lamps turned by a quarter; turned by 180 degrees; the centre lamp swapped with
  the right one, and with the upper one; the right and upper lamps swapped; the centre lamp
  listed last. And each set of four of the five with each two of its lamps swapped that are
  not mirror images (the swap changes the span of the lights, so the residual can see it).
- Each subject's `--random` sets of five of the 64 lights (mean-equalised frames, as read),
  with the lights as given: where the shadows of wide lights break the least-squares normals.
  Within 50 degrees, also `--random` sets of four. For the sets of four and the swaps, the
  residual ratio also with the mean over the cells in place of the median.
- Leave one subject out: the curl, convexity and order thresholds, and the residual's slack
  (`RESIDUAL_SLACK`: the four-light threshold midway, geometrically, between the largest
  ratio as given and the smallest swapped, minus 1), each from the other four subjects.
- psm's cat and owl, under its twelve lights, inside their masks.
- Its time on the synthetic face's five frames, 192x168 and 1280x1024 (median of 7).
- Away from the shared data: the synthetic face of `jaxps.synthetic.face_like` under the
  scanner's five lights, at three noise levels, and a flat, tilted plane, as given and
  mirrored.

    PYTHONPATH=src python benchmarks/light_check.py -> benchmarks/results/light_check.json
"""

from __future__ import annotations

import itertools
import logging
import pathlib
import sys
import time

import numpy as np

import jaxps
from jaxps import acquisition as acq
from jaxps import synthetic
from jaxps.lights import _check

try:
    from benchmarks._common import arguments, data_dir, environment, write_json
except ImportError:  # run as a script
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    from benchmarks._common import arguments, data_dir, environment, write_json

CROSS = ["A+000E+00", "A+025E+00", "A-025E+00", "A+000E+20", "A+000E-20"]
# The five cross lights in CROSS's order: centre, right of the image (+25 lights the left),
# left, above, below. Each wrong lights file as a function of the right one.
WRONG = {
    "y negated": lambda l: l * [1, -1, 1],
    "x negated": lambda l: l * [-1, 1, 1],
    "left and right swapped": lambda l: l[[0, 2, 1, 3, 4]],
    "quarter turn": lambda l: l[[0, 3, 4, 2, 1]],
    "180 degrees": lambda l: l[[0, 2, 1, 4, 3]],
    "centre and one outer swapped": lambda l: l[[1, 0, 2, 3, 4]],
    "centre and upper swapped": lambda l: l[[3, 1, 2, 0, 4]],
    "right and upper swapped": lambda l: l[[0, 3, 2, 1, 4]],
    "centre listed last": lambda l: l[[1, 2, 3, 4, 0]],
}
# The wrong orders above that change the span of the lights (not mirror images).
SPAN_CHANGED = ("centre and one outer swapped", "centre and upper swapped",
                "right and upper swapped", "centre listed last")


def _figures(images, lights, mask=None, max_zenith_deg=50.0):
    c = jaxps.check_lights(images, lights, mask=mask, max_zenith_deg=max_zenith_deg)
    return {"curl": round(c.curl, 4), "convexity": round(c.convexity, 4), "mirrored": c.mirrored,
            "reordered": c.reordered, "best_order": c.best_order,
            "best_curl": round(c.best_curl, 4), "residual_ratio": round(c.residual_ratio, 3),
            "hollow": c.hollow, "loops": c.loops,
            "block": c.block, "unchecked": c.unchecked}


def yale(data, random_sets):
    out = {}
    rng = np.random.default_rng(0)
    for folder in sorted((data / "yaleb").glob("yaleB*")):
        s = folder.name
        ambient = folder / f"{s}_P00_Ambient.pgm"
        cap = acq.load_capture([folder / f"{s}_P00{n}.pgm" for n in CROSS], yale_names=True,
                               ambient=ambient)
        if len(cap.names) != len(CROSS):  # B02: the frame check drops a combed frame
            cap = acq.load_capture([folder / f"{s}_P00{n}.pgm" for n in CROSS],
                                   yale_names=True, ambient=ambient, check_quality=False)
        lights = np.asarray(cap.lights, np.float64)
        row = {"given": _figures(cap.images, lights, cap.mask)}
        for name, wrong in WRONG.items():
            row[name] = _figures(cap.images, wrong(lights), cap.mask)
        row["four lamps, two swapped"] = _four_swapped(cap.images, lights, cap.mask)
        every = acq.load_capture(folder, yale_names=True, ambient=ambient, intensities="mean",
                                 register=False)
        for zenith in (180, 50):
            label = ("random five of 64" if zenith == 180 else
                     f"random five within {zenith} deg") + ", given"
            row[label] = _random_sets(every, zenith, random_sets, rng)
        row["random four within 50 deg, given"] = _random_sets(every, 50, random_sets, rng, 4)
        out[s] = row
    return out


def _mean_ratio(images, lights, mask=None):
    """The residual ratio `check_lights` would give with the mean over the cells in place of
    the median (`_residuals(average=np.mean)`), on the same cells and orders."""
    grey = np.asarray(images, np.float32)
    grey = grey if grey.ndim == 3 else grey.mean(axis=-1)
    mask = np.ones(grey.shape[1:], bool) if mask is None else np.asarray(mask, bool)
    g, keep, _ = _check._cells(grey, mask)
    residual = _check._residuals(g, keep, lights[_check._orders(len(lights))], np.mean)
    return float(residual[0] / residual.min())


def _four_swapped(images, lights, mask):
    """Each set of four of the five cross frames, with each two of its lamps swapped whose
    swap changes the span of the lights (mirror-image swaps are the curl's to see): the
    smallest residual ratio and how many were called reordered."""
    ratios, means, caught = [], [], 0
    for sub in itertools.combinations(range(len(lights)), 4):
        sub = list(sub)
        span = lights[sub] @ np.linalg.pinv(lights[sub])
        for i, j in itertools.combinations(range(4), 2):
            order = np.arange(4)
            order[[i, j]] = [j, i]
            wrong = lights[sub][order]
            if np.allclose(wrong @ np.linalg.pinv(wrong), span, atol=1e-6):
                continue
            c = jaxps.check_lights(images[sub], wrong, mask=mask)
            ratios.append(c.residual_ratio)
            means.append(_mean_ratio(images[sub], wrong, mask))
            caught += c.reordered
    return {"swaps": len(ratios), "residual_ratio_min": float(min(ratios)),
            "mean_residual_ratio_min": float(min(means)), "reordered": caught}


def _random_sets(capture, zenith, count, rng, k=5):
    """`count` random sets of `k` of `capture`'s lights within `zenith` degrees of the view
    axis, as given: the largest curl, convexity and residual ratio, and how many sets were
    flagged."""
    near = np.flatnonzero(capture.lights[:, 2] >= np.cos(np.radians(zenith)) - 1e-6)
    sets = []
    for _ in range(count):
        pick = rng.choice(near, k, replace=False)
        try:
            sets.append(_figures(capture.images[pick], capture.lights[pick],
                                 max_zenith_deg=zenith))
        except ValueError:  # five lights that do not span 3-D
            continue
        if k == 4:
            sets[-1]["mean_residual_ratio"] = _mean_ratio(capture.images[pick],
                                                          capture.lights[pick])
    curl = np.array([r["curl"] for r in sets])
    convexity = np.array([r["convexity"] for r in sets])
    gap = curl - np.array([r["best_curl"] for r in sets])
    return {"lights_to_pick_from": len(near), "sets": len(sets),
            "not_measured": int(np.isnan(curl).sum()), "curl_max": float(np.nanmax(curl)),
            "curl_median": float(np.nanmedian(curl)),
            "convexity_max": float(np.nanmax(convexity)),
            "order_gap_max": float(np.nanmax(gap)),
            "residual_ratio_max": float(np.nanmax([r["residual_ratio"] for r in sets])),
            **({"mean_residual_ratio_max": float(np.nanmax([r["mean_residual_ratio"]
                                                            for r in sets]))}
               if k == 4 else {}),
            "flagged": sum(r["mirrored"] or r["reordered"] or r["hollow"] for r in sets),
            "unchecked": sum(bool(r["unchecked"]) for r in sets)}


def psm(data):
    lights = jaxps.load_lights(data / "psm" / "lights.txt")
    # A lights file listed in the order of the frame names sorted as text (cat.0, cat.1,
    # cat.10, cat.11, cat.2, ...), for frames read in natural order.
    text = sorted(range(len(lights)), key=lambda k: f"cat.{k}.png")
    out = {}
    for obj in ("cat", "owl"):
        images, mask = jaxps.load_psm(data / "psm" / obj)
        out[obj] = {"given": _figures(images, lights, mask > 0.5),
                    "y negated": _figures(images, lights * [1, -1, 1], mask > 0.5),
                    "180 degrees": _figures(images, lights * [-1, -1, 1], mask > 0.5),
                    "names sorted as text": _figures(images, lights[text], mask > 0.5),
                    "lamps 0 and 6 swapped (12 deg apart)": _figures(
                        images, lights[[6, 1, 2, 3, 4, 5, 0, 7, 8, 9, 10, 11]], mask > 0.5),
                    "lamps 0 and 4 swapped (43 deg apart)": _figures(
                        images, lights[[4, 1, 2, 3, 0, 5, 6, 7, 8, 9, 10, 11]], mask > 0.5),
                    "every two lamps swapped": _psm_swaps(images, lights, mask > 0.5)}
    return out


def _psm_swaps(images, lights, mask):
    """Every two of the twelve lamps swapped, by how far apart they are: how many were
    called reordered, and the residual ratios."""
    apart = np.degrees(np.arccos(np.clip(lights @ lights.T, -1, 1)))
    bands = {"under 10 deg": (0, 10), "10-20 deg": (10, 20), "20-30 deg": (20, 30),
             "30 deg or more": (30, 180)}
    out = {band: {"swaps": 0, "reordered": 0, "residual_ratios": []} for band in bands}
    for i, j in itertools.combinations(range(len(lights)), 2):
        order = np.arange(len(lights))
        order[[i, j]] = [j, i]
        c = jaxps.check_lights(images, lights[order], mask=mask)
        band = next(b for b, (lo, hi) in bands.items() if lo <= apart[i, j] < hi)
        out[band]["swaps"] += 1
        out[band]["reordered"] += c.reordered
        out[band]["residual_ratios"].append(round(c.residual_ratio, 2))
    return out


def synthetic_scenes():
    lights = np.asarray(synthetic.scanner_lights(20.0), np.float64)
    out = {}
    face = synthetic.face_like(200)
    for noise in (0.0, 0.01, 0.03):
        images = np.asarray(synthetic.render_scene(face, lights, noise=noise, key=1).images)
        out[f"face, noise {noise}"] = {
            "given": _figures(images, lights, face.mask),
            **{name: _figures(images, wrong(lights), face.mask)
               for name, wrong in WRONG.items()}}
    n = np.array([0.2, -0.1, 1.0]) / np.linalg.norm([0.2, -0.1, 1.0])
    plane = np.clip(lights @ n, 0, None)[:, None, None] * np.ones((5, 160, 160))
    images = plane + 0.01 * np.random.default_rng(1).standard_normal(plane.shape)
    out["tilted plane, noise 0.01"] = {"given": _figures(images, lights),
                                       "y negated": _figures(images, lights * [1, -1, 1])}
    return out


def timing(repeats=7):
    """Median seconds of `check_lights` on the synthetic face's five frames at two sizes."""
    lights = np.asarray(synthetic.scanner_lights(20.0), np.float64)
    out = {}
    for h, w in ((192, 168), (1024, 1280)):
        images = np.asarray(synthetic.render_scene(synthetic.face_like(h, w), lights).images)
        times = []
        for _ in range(repeats):
            t = time.perf_counter()
            jaxps.check_lights(images, lights)
            times.append(time.perf_counter() - t)
        out[f"{h}x{w}x5"] = float(np.median(times))
    return out


def leave_one_out(yaleb):
    """Each subject held out: the thresholds midway between the other four's figures with the
    lights as given (the cross and the random sets within 50 degrees) and wrong (mirrored:
    y negated, x negated, left and right swapped; turned by 180 degrees; for the order
    margin, the quarter turn and the left-right swap), and whether they tell the held-out
    subject's right lights from its wrong ones."""
    def figures(row):
        random = row["random five within 50 deg, given"]
        gap = lambda r: r["curl"] - r["best_curl"]
        return {"gap_right": max(gap(row["given"]), random["order_gap_max"]),
                "gap_wrong": min(gap(row[k]) for k in ("quarter turn", "left and right swapped")),
                "curl_right": max(row["given"]["curl"], random["curl_max"]),
                "curl_mirrored": min(row[k]["curl"] for k in
                                     ("y negated", "x negated", "left and right swapped")),
                "convexity_right": max(row["given"]["convexity"], random["convexity_max"]),
                "convexity_turned": row["180 degrees"]["convexity"]}
    def residuals(row):
        return {"right": {k: row[f"random {w} within 50 deg, given"]["residual_ratio_max"]
                          for k, w in ((4, "four"), (5, "five"))},
                "wrong": {4: row["four lamps, two swapped"]["residual_ratio_min"],
                          5: min(row[k]["residual_ratio"] for k in SPAN_CHANGED)}}
    res = {s: residuals(row) for s, row in yaleb.items()}
    per = {s: figures(row) for s, row in yaleb.items()}
    out = {}
    for held, f in per.items():
        rest = [v for s, v in per.items() if s != held]
        curl = 0.5 * (max(v["curl_right"] for v in rest) + min(v["curl_mirrored"] for v in rest))
        conv = 0.5 * (max(v["convexity_right"] for v in rest)
                      + min(v["convexity_turned"] for v in rest))
        gap = 0.5 * (max(v["gap_right"] for v in rest) + min(v["gap_wrong"] for v in rest))
        others = [v for s, v in res.items() if s != held]
        slack = np.sqrt(max(v["right"][4] for v in others)
                        * min(v["wrong"][4] for v in others)) - 1
        factor = {k: 1 + slack / (k - 3) for k in (4, 5)}
        mine = res[held]
        out[held] = {"curl_threshold": round(curl, 3), "convexity_threshold": round(conv, 3),
                     "order_margin": round(gap, 3), "residual_slack": round(float(slack), 3),
                     "residual_right_passes": all(mine["right"][k] <= factor[k] for k in (4, 5)),
                     "residual_wrong_flagged": all(mine["wrong"][k] > factor[k]
                                                   for k in (4, 5)),
                     "right_passes": (f["curl_right"] <= curl and f["convexity_right"] <= conv
                                      and f["gap_right"] <= gap),
                     "wrong_flagged": (f["curl_mirrored"] > curl and f["convexity_turned"] > conv
                                       and f["gap_wrong"] > gap)}
    return out


def main():
    args = arguments(__doc__, configure=lambda p: p.add_argument(
        "--random", type=int, default=200, help="random five-light sets per Yale B subject"))
    data = data_dir()
    if not (data / "psm").is_dir() or not (data / "yaleb").is_dir():
        sys.exit(f"needs the shared data (psm/ and yaleb/) under {data}")
    logging.getLogger("jaxps").setLevel(logging.ERROR)  # the frame check's list of wide lights
    result = {"environment": environment(), "random_sets": args.random,
              "yaleb": yale(data, args.random), "psm": psm(data),
              "synthetic": synthetic_scenes()}
    result["leave_one_subject_out"] = leave_one_out(result["yaleb"])
    result["seconds"] = timing()
    for group in ("yaleb", "psm", "synthetic"):
        for name, row in result[group].items():
            cells = [f"{k} {v['curl']:.2f}/{v['convexity']:+.2f}"
                     f"{' M' if v.get('mirrored') else ''}{' H' if v.get('hollow') else ''}"
                     f"{' R ' + str(v['best_order']) + ' ' + format(v['best_curl'], '.2f') if v.get('reordered') else ''}"
                     for k, v in row.items() if "curl" in v]
            extra = [f"{k}: curl max {v['curl_max']:.2f}, median {v['curl_median']:.2f}, "
                     f"convexity max {v['convexity_max']:+.2f}, order gap max "
                     f"{v['order_gap_max']:.2f}, residual ratio max "
                     f"{v['residual_ratio_max']:.2f}; {v['flagged']} of {v['sets']} "
                     f"flagged, {v['not_measured']} not measured"
                     for k, v in row.items() if "curl_max" in v]
            extra += [f"{k}: residual ratio min {v['residual_ratio_min']:.2f} (with the mean "
                      f"over cells {v['mean_residual_ratio_min']:.2f}), "
                      f"{v['reordered']} of {v['swaps']} reordered"
                      for k, v in row.items() if "residual_ratio_min" in v]
            extra += [f"{k}: with the mean over cells, residual ratio max "
                      f"{v['mean_residual_ratio_max']:.2f}"
                      for k, v in row.items() if "mean_residual_ratio_max" in v]
            extra += [f"{k}: " + ", ".join(f"{band} {b['reordered']} of {b['swaps']}"
                                          for band, b in v.items())
                      for k, v in row.items() if k == "every two lamps swapped"]
            print(f"{name}: " + "; ".join(cells + extra))
    for held, r in result["leave_one_subject_out"].items():
        print(f"{held} held out: curl threshold {r['curl_threshold']:.2f}, convexity "
              f"{r['convexity_threshold']:+.2f}, order margin {r['order_margin']:.2f}, "
              f"residual slack {r['residual_slack']:.2f} from the others; its right lights "
              f"pass: {r['right_passes']} (residual {r['residual_right_passes']}), its wrong "
              f"ones flagged: {r['wrong_flagged']} (residual {r['residual_wrong_flagged']})")
    print("check_lights: " + ", ".join(f"{k} {1e3 * v:.1f} ms"
                                       for k, v in result["seconds"].items()))
    print(write_json("light_check", result))


if __name__ == "__main__":
    main()
