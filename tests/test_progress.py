"""Progress on long library calls: what their hooks hear, what the bar prints, what is timed,
and that showing progress changes no result."""

import io

import numpy as np

import jaxps
from jaxps import report, stability
from jaxps.core._progress import Stages


def recorder():
    calls = []
    return calls, lambda stage, done, total: calls.append((stage, done, total))


def test_stages_time_each_stage_and_tell_the_hook():
    import jax.numpy as jnp

    calls, hook = recorder()
    with Stages(2, hook) as stages:
        a = stages.run("square", lambda x: x * x, jnp.arange(4.0))
        b = stages.run("sum", jnp.sum, a, time_key="total")
    assert float(b) == 14.0
    assert calls == [("square", 0, 2), ("sum", 1, 2), ("", 2, 2)]
    assert list(stages.times) == ["square", "total"]
    assert all(t >= 0 for t in stages.times.values())

    with Stages(1) as quiet:  # no hook: timed all the same
        quiet.run("silent", lambda: 1)
    assert list(quiet.times) == ["silent"]


def test_progress_bar_names_each_stage_and_closes():
    out = io.StringIO()
    hook = report.progress_bar(out)
    for stage, done in (("load", 0), ("fit", 1), ("", 2)):
        hook(stage, done, 2)
    text = out.getvalue()
    assert "load (1/2)" in text and "fit (2/2)" in text


def test_brdf_photometric_stereo_progress():
    surf = jaxps.synthetic.face_like(20)
    lights = stability.ring_lights(6, 35.0)
    images = jaxps.synthetic.render_scene(surf, lights).images
    kw = {"mask": np.asarray(surf.mask), "method": "lambertian", "iterations": 2, "max_steps": 3}
    quiet = jaxps.brdf_photometric_stereo(images, lights, **kw)
    calls, hook = recorder()
    shown = jaxps.brdf_photometric_stereo(images, lights, progress=hook, **kw)
    assert calls == [("L2 photometric stereo", 0, 5), ("fit lambertian (1/2)", 1, 5),
                     ("re-solve pixels (1/2)", 2, 5), ("fit lambertian (2/2)", 3, 5),
                     ("re-solve pixels (2/2)", 4, 5), ("", 5, 5)]
    assert list(shown.info["times_s"]) == ["l2", "fit 1", "solve 1", "fit 2", "solve 2"]
    assert list(quiet.info["times_s"]) == list(shown.info["times_s"])
    for a, b in zip(quiet[:5], shown[:5]):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_sweep_progress():
    kw = {"values": (0.0, 2.0), "methods": ("l2", "irls"), "h": 24, "key": 3}
    quiet = stability.sweep("light_error_deg", **kw)
    calls, hook = recorder()
    shown = stability.sweep("light_error_deg", progress=hook, **kw)
    assert [c[0] for c in calls] == ["light_error_deg=0: l2", "light_error_deg=0: irls",
                                     "light_error_deg=2: l2", "light_error_deg=2: irls", ""]
    assert shown == quiet


def test_progress_bar_writes_warnings_above_itself():
    """A library user's bar: a warning of the `jaxps` logger during a stage is a line of its
    own (until the thirtieth session Python's fallback handler wrote it into the bar's line).
    Run in a fresh interpreter: pytest sets up logging handlers of its own."""
    import os
    import subprocess
    import sys

    from conftest import ROOT

    script = """
import logging
from jaxps import report
hook = report.progress_bar()
hook("first stage", 0, 2)
logging.getLogger("jaxps").warning("something odd")
hook("second stage", 1, 2)
hook("", 2, 2)
print(len(logging.getLogger("jaxps").handlers))
"""
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src")}
    proc = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True,
                          text=True, timeout=120, check=True)
    lines = [line.split("\r")[-1].rstrip() for line in proc.stderr.split("\n")]
    assert "something odd" in lines, proc.stderr
    assert "first stage" in proc.stderr and "second stage" in proc.stderr
    assert proc.stdout.strip() == "0"  # the handler leaves with the bar
