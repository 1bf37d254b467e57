"""Issue 17's command line on real faces with one of the five frames spoilt.

    OPENBLAS_NUM_THREADS=1 JAXPS_DATA=../shared/data PYTHONPATH=src \\
        python benchmarks/spoilt_frames.py [--out NAME]

For each Yale B subject (every `yaleB*` folder of the data), `jaxps reconstruct FRAMES
--yale-names --ambient A` (nothing else) runs on the five cross frames (0,0), (+-25,0), (0,+-20)
as read, and again with one frame spoilt the way a scanner spoils one (the raw 8-bit codes):

- `combed_frontal`: the (0,0) frame interlace-combed (odd rows 3 px along, at 70%), as two
  of yaleB02's frames are;
- `misfire_+25`: the (+25,0) flash did not fire (the ambient frame, 2 codes up);
- `moved_+20`: the (0,+20) frame moved 5 px sideways (`np.roll`), as a walking subject would;
- `overexposed_-25`: the (-25,0) frame 2.5 times as bright, clipped at 255.

And a capture that is not in the shared data: a walk-through at 1280x1024, the rendered face
(`synthetic.face_like`, `scanner_lights(20)`, 0.5% noise, 16-bit PNGs) walking 3 px sideways
from each frame to the next (frame k moved 3k px, up to 12), solved by `jaxps reconstruct
FRAMES --lights lights.txt` and scored against its known normals where it was rendered
(frame 0, the frontal one, stays put).

And every frame of each subject's folder (64 lights, up to 130 degrees off axis) through
`load_capture` with its defaults and `photometric_stereo`, against the same reference: how
many frames are kept and registered, the off-axis angles of those dropped as moved, and the
median error (`whole_folder`).

Per run: the exit status, the frames dropped with their reasons and the motion measured
between the frames kept (`summary.json`), the
command's error when it stopped, and the median angular error of the normals it wrote
(`normals.png`, OK pixels) against `bench_faces.py`'s semi-calibrated many-light reference
(frames as read) over the reference's evaluation region. Writes
`benchmarks/results/NAME.json` (default `spoilt_frames`).
"""

from __future__ import annotations

import contextlib
import io
import json
import pathlib
import sys
import tempfile

import numpy as np

import jaxps

try:
    from benchmarks._common import arguments, environment, write_json
except ImportError:  # run as a script
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    from benchmarks._common import arguments, environment, write_json

from benchmarks import bench_faces as bf

SPOILS = ("clean", "combed_frontal", "misfire_+25", "moved_+20", "overexposed_-25")


def _name(subject, azimuth, elevation):
    return f"{subject}_P00A{azimuth:+04d}E{elevation:+03d}.pgm"


def spoil(kind: str, raw: dict, ambient: np.ndarray) -> dict:
    """The five raw uint8 frames keyed by (azimuth, elevation), one of them spoilt."""
    raw = {k: v.copy() for k, v in raw.items()}
    if kind == "combed_frontal":
        f = raw[(0, 0)].astype(float)
        f[1::2] = np.roll(f[1::2], 3, axis=1) * 0.7
        raw[(0, 0)] = np.clip(f, 0, 255).astype(np.uint8)
    elif kind == "misfire_+25":
        raw[(25, 0)] = np.clip(ambient.astype(int) + 2, 0, 255).astype(np.uint8)
    elif kind == "moved_+20":
        raw[(0, 20)] = np.roll(raw[(0, 20)], 5, axis=1)
    elif kind == "overexposed_-25":
        raw[(-25, 0)] = np.clip(raw[(-25, 0)].astype(float) * 2.5, 0, 255).astype(np.uint8)
    return raw


def run(subject: str, kind: str, raw: dict, ambient: np.ndarray, reference, region) -> dict:
    """`jaxps reconstruct` on the spoilt frames, in this process."""
    import cv2

    from jaxps.cli import main as cli
    from jaxps.report._writers import read_normal_map

    with tempfile.TemporaryDirectory() as tmp:
        tmp = pathlib.Path(tmp)
        paths = []
        for key, frame in spoil(kind, raw, ambient).items():
            paths.append(tmp / _name(subject, *key))
            cv2.imwrite(str(paths[-1]), frame)
        cv2.imwrite(str(tmp / "ambient.pgm"), ambient)
        out, err = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                status = cli(["reconstruct", *map(str, paths), "--yale-names", "--ambient",
                              str(tmp / "ambient.pgm"), "--out", str(tmp / "run")])
            except SystemExit as stop:
                status = stop.code
        row = {"exit_status": status, "median_deg": None, "frames_solved": None,
               "dropped": {}, "error": None}
        summary = tmp / "run" / "summary.json"
        if summary.is_file():
            info = json.loads(summary.read_text())
            row["dropped"] = info.get("dropped_why", {})
            row["frames_solved"] = len(info["frames"])
            row["motion"] = info.get("motion")
            normals = read_normal_map(tmp / "run" / "normals.png")
            ok = np.load(tmp / "run" / "status.npy") == 0
            angle = np.asarray(jaxps.angular_error(normals, reference))
            row["median_deg"] = float(np.median(angle[region & ok]))
        else:
            row["error"] = next((line for line in err.getvalue().splitlines()
                                 if "error:" in line), err.getvalue()[-300:])
    return row


def walk_through(step: int = 3) -> dict:
    """The rendered 1 MP face walking `step` px a frame (frame k moved k * step px)."""
    import cv2

    from jaxps.cli import main as cli
    from jaxps.report._writers import read_normal_map

    surface = jaxps.synthetic.face_like(1024, 1280)
    lights = jaxps.synthetic.scanner_lights(20.0)
    frames = np.asarray(jaxps.synthetic.render_scene(surface, lights, noise=0.005, key=0).images)
    region = np.array(surface.mask)
    region[:, -4 * step - 8:] = False  # where the last frame's face left the picture
    with tempfile.TemporaryDirectory() as tmp:
        tmp = pathlib.Path(tmp)
        jaxps.save_lights(tmp / "lights.txt", lights)
        paths = []
        for k, frame in enumerate(frames):
            paths.append(tmp / f"frame{k}.png")
            moved = np.roll(frame, k * step, axis=1)  # the face is on black: nothing wraps
            cv2.imwrite(str(paths[-1]), np.round(np.clip(moved, 0, 1) * 65535).astype(np.uint16))
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            status = cli(["reconstruct", *map(str, paths), "--lights", str(tmp / "lights.txt"),
                          "--out", str(tmp / "run")])
        info = json.loads((tmp / "run" / "summary.json").read_text())
        ok = np.load(tmp / "run" / "status.npy") == 0
        angle = np.asarray(jaxps.angular_error(read_normal_map(tmp / "run" / "normals.png"),
                                               surface.normals))
    row = {"exit_status": status, "step_px": step, "motion": info.get("motion"),
           "dropped": info.get("dropped_why", {}),
           "median_deg": float(np.median(angle[region & ok])),
           "solved_fraction": float((region & ok).sum() / region.sum())}
    print(f"walk-through 1280x1024, {step} px a frame: exit {status}  "
          f"{row['median_deg']:.2f} deg  registered {info['motion']['registered']}", flush=True)
    return row


def whole_folder(subject: str, reference, region) -> dict:
    """All 64 frames of the folder through `load_capture` and `photometric_stereo`."""
    from jaxps.acquisition import load_capture

    folder = bf.data_dir() / "yaleb" / subject
    paths = sorted(folder.glob(f"{subject}_P00A*.pgm"))
    cap = load_capture(paths, yale_names=True, ambient=folder / f"{subject}_P00_Ambient.pgm")
    res = jaxps.photometric_stereo(cap.images, cap.lights, mask=cap.mask,
                                   sample_mask=~cap.saturated)
    angle = np.asarray(jaxps.angular_error(res.normals, reference))
    moved = [jaxps.parse_yale_name(f.name) for f in cap.frame_check.flagged
             if f.reasons[0].startswith("moved")]
    row = {"frames": len(paths), "kept": len(cap.names), "registered": bool(cap.registered),
           "largest_kept_shift_px": float(np.abs(np.asarray(cap.shifts)).max()),
           "dropped_as_moved_off_axis_deg": sorted(round(float(bf.off_axis(a, e)))
                                                   for a, e in moved),
           "median_deg": float(np.median(angle[region & (np.asarray(res.status) == 0)]))}
    print(f"{subject} whole folder: {row['kept']} of {row['frames']} frames kept, registered "
          f"{row['registered']}, {row['median_deg']:.2f} deg; dropped as moved at "
          f"{row['dropped_as_moved_off_axis_deg']} deg off axis", flush=True)
    return row


def subject_rows(subject: str) -> dict:
    import cv2

    folder = bf.data_dir() / "yaleb" / subject
    raw = {k: cv2.imread(str(folder / _name(subject, *k)), cv2.IMREAD_UNCHANGED)
           for k in bf.CROSS}
    ambient = cv2.imread(str(folder / f"{subject}_P00_Ambient.pgm"), cv2.IMREAD_UNCHANGED)
    frames = bf.load_subject(subject)
    keys, _ = bf.clean(frames, sorted(k for k in frames if bf.off_axis(*k) <= bf.MAX_ANGLE))
    ref = bf.semi(frames, keys)
    region = (np.asarray(ref.status == 0) & np.asarray(ref.albedo > bf.ALBEDO_MIN)
              & bf.inner(ref.status.shape))
    rows = {"whole_folder": whole_folder(subject, np.asarray(ref.normals), region)}
    for kind in SPOILS:
        rows[kind] = row = run(subject, kind, raw, ambient, np.asarray(ref.normals), region)
        deg = "-" if row["median_deg"] is None else f"{row['median_deg']:.2f}"
        print(f"{subject} {kind:<16} exit {row['exit_status']}  {deg:>5} deg  "
              f"dropped {list(row['dropped']) or '-'}{'  ' + row['error'] if row['error'] else ''}",
              flush=True)
    return rows


def main(argv=None) -> None:
    args = arguments(__doc__, argv=argv, configure=lambda p: p.add_argument(
        "--out", default="spoilt_frames", help="results name (default spoilt_frames)"))
    out = {"environment": environment(), "walk_through_1280x1024": walk_through()}
    if (bf.data_dir() / "yaleb").is_dir():
        out["subjects"] = {s: subject_rows(s) for s in bf.SUBJECTS}
    else:
        print(f"no Yale B captures in {bf.data_dir()} (set JAXPS_DATA): rendered face only")
    print("wrote", write_json(args.out, out))


if __name__ == "__main__":
    main()
