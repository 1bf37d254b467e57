"""The store of compiled programs (`core._store`): what one process compiles, the next loads
without tracing, with the same results; a changed code fingerprint or a broken file
compiles afresh; calls inside a trace pass through."""

import json
import os
import subprocess
import sys

import jax
import numpy as np
import pytest

import jaxps
from jaxps.core import _store

# One fresh process: JAX's persistent cache and the store in `folder` (or the cache alone, or
# neither), then L2 (clean and dropping samples) and FC / DCT / LSQ integration on a small face.
# Prints the store's counts and writes the results to `out`.
_SCRIPT = """
import json, sys
import numpy as np
import jaxps
from jaxps.cli import enable_compilation_cache
from jaxps.core import _store
folder, mode, out = sys.argv[1:]
if mode != "off":
    enable_compilation_cache(folder)
if mode == "jax cache only":
    _store.use_store(None)
import pathlib
import jax
def jax_entries():  # the files of JAX's own cache
    return sum(1 for p in pathlib.Path(folder).glob("*") if p.is_file())
jax.jit(lambda a: a + 1)(np.ones(3))  # JAX decides here whether its cache is in use
surface = jaxps.synthetic.face_like(40, 32)
lights = jaxps.synthetic.scanner_lights(20.0)
images = np.asarray(jaxps.synthetic.render_scene(surface, lights).images)
clean = jaxps.photometric_stereo(images, lights)
dropped = jaxps.photometric_stereo(images, lights, shadow_threshold=0.05)
arrays = {f"{name}_{field}": np.asarray(getattr(res, field))
          for name, res in (("clean", clean), ("dropped", dropped))
          for field in ("normals", "albedo", "status", "n_used", "residual")}
arrays["fc"] = np.asarray(jaxps.integrate(clean.normals))
arrays["dct"] = np.asarray(jaxps.integrate(clean.normals, method="dct"))
arrays["lsq"] = np.asarray(jaxps.integrate(clean.normals, mask=surface.mask, method="lsq"))
np.savez(out, **arrays)
before = jax_entries()
import os
jax.jit(lambda a: a * 3.5 + 2)(np.ones(8 + os.getpid()))  # one of its own, after the store's
print(json.dumps({**_store.stats(), "jax_cache_written": jax_entries() > before}))
"""


def _run(folder, mode, out):
    proc = subprocess.run([sys.executable, "-c", _SCRIPT, str(folder), mode, str(out)],
                          capture_output=True, text=True, timeout=600, check=False,
                          env={**os.environ, "JAXPS_CACHE_DIR": str(folder)})
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_a_new_process_loads_what_the_last_one_compiled_with_the_same_results(tmp_path):
    folder = tmp_path / "cache"
    # JAX's own cache filled first, and in use before the store's first compile: the store
    # must not serialize what JAX read back from it (such an executable serializes without
    # its machine code and fails once loaded), and must leave JAX's cache on
    _run(folder, "jax cache only", tmp_path / "jax_cache.npz")
    first = _run(folder, "store", tmp_path / "first.npz")
    second = _run(folder, "store", tmp_path / "second.npz")
    plain = _run(tmp_path / "unused", "off", tmp_path / "plain.npz")
    # with the store on, L2's solve is chosen on the host: one flag pass (the thresholds are
    # arguments), the clean and the weighted solve, and two programs each for FC, DCT and LSQ
    # (`jaxps reconstruct`'s default); JAX's cache still takes the programs not in the store
    assert first == {"loaded": 0, "compiled": 9, "plain": 0, "jax_cache_written": True}
    assert second == {"loaded": 9, "compiled": 0, "plain": 0, "jax_cache_written": True}
    assert plain == {"loaded": 0, "compiled": 0, "plain": 0, "jax_cache_written": False}
    assert len(list((folder / "executables").glob("*.exe"))) == 9
    ref = np.load(tmp_path / "plain.npz")
    for name in ("jax_cache", "first", "second"):
        got = np.load(tmp_path / f"{name}.npz")
        for key in ref.files:
            np.testing.assert_array_equal(got[key], ref[key], err_msg=f"{name} {key}")


@pytest.fixture
def store(tmp_path, monkeypatch):
    """The store on in `tmp_path` for this test only, with counts from zero."""
    for name, value in (("_folder", None), ("_executables", {}), ("_fingerprint", None),
                        ("_stats", {"loaded": 0, "compiled": 0, "plain": 0})):
        monkeypatch.setattr(_store, name, value)
    _store.use_store(tmp_path)
    return tmp_path


def _normals():
    surface = jaxps.synthetic.face_like(24, 20)
    return np.asarray(surface.normals), np.asarray(surface.mask)


def _integrate_fc(normals):
    from jaxps.integration._integrate import _fc_spectrum_from_normals

    return _store.call(_fc_spectrum_from_normals, normals, np.ones(normals.shape[:2], bool),
                       np.float32(1.0))


def test_a_changed_fingerprint_or_a_broken_file_compiles_afresh(store, monkeypatch):
    normals, _ = _normals()
    want = _integrate_fc(normals)
    assert _store.stats()["compiled"] == 1
    monkeypatch.setattr(_store, "_executables", {})  # as a new process
    np.testing.assert_array_equal(_integrate_fc(normals)[0], want[0])
    assert _store.stats()["loaded"] == 1
    # new code: another fingerprint, another key
    monkeypatch.setattr(_store, "_executables", {})
    monkeypatch.setattr(_store, "_fingerprint", "another version of jaxps")
    np.testing.assert_array_equal(_integrate_fc(normals)[0], want[0])
    assert _store.stats()["compiled"] == 2
    assert len(list(store.glob("*.exe"))) == 2
    # a torn or foreign file: removed, compiled again
    for path in store.glob("*.exe"):
        path.write_bytes(b"not an executable")
    monkeypatch.setattr(_store, "_executables", {})
    np.testing.assert_array_equal(_integrate_fc(normals)[0], want[0])
    assert _store.stats() == {"loaded": 1, "compiled": 3, "plain": 0}


def test_calls_inside_a_trace_or_with_the_store_off_pass_through(store):
    surface = jaxps.synthetic.face_like(24, 20)
    lights = jaxps.synthetic.scanner_lights(20.0)
    images = np.asarray(jaxps.synthetic.render_scene(surface, lights).images)
    inside = jax.jit(lambda x: jaxps.photometric_stereo(x, lights).normals)(images)
    assert _store.stats() == {"loaded": 0, "compiled": 0, "plain": 0}
    assert not list(store.glob("*.exe"))
    _store.use_store(None)
    np.testing.assert_allclose(jaxps.photometric_stereo(images, lights).normals, inside,
                               atol=1e-6)
    assert _store.stats() == {"loaded": 0, "compiled": 0, "plain": 0}


# One fresh process with the store in `folder`: a jitted LAPACK solve through the store,
# before anything else of JAX's linear algebra is lowered in the process.
_LAPACK_SCRIPT = """
import json, sys
import jax, numpy as np
from jaxps.core import _store
_store.use_store(sys.argv[1])
solve = jax.jit(lambda a, b: jax.numpy.linalg.solve(a, b))
a = np.array([[4.0, 1.0, 0.0], [1.0, 3.0, 1.0], [0.0, 1.0, 2.0]], np.float32)
b = np.array([1.0, 2.0, 3.0], np.float32)
x = _store.call(solve, a, b)
print(json.dumps({**_store.stats(), "error": float(np.max(np.abs(x - np.linalg.solve(a, b))))}))
"""


def test_a_lapack_program_is_stored_and_runs_in_a_process_that_only_loads_it(tmp_path):
    """jaxlib sets a LAPACK call's function pointer when it lowers such a call; a process that
    only loads the executable crashed (SIGSEGV) until the store set them up before loading."""
    def run():
        proc = subprocess.run([sys.executable, "-c", _LAPACK_SCRIPT, str(tmp_path)],
                              capture_output=True, text=True, timeout=300, check=False)
        assert proc.returncode == 0, (proc.returncode, proc.stderr[-3000:])
        return json.loads(proc.stdout.strip().splitlines()[-1])

    first, second = run(), run()
    assert {k: first[k] for k in ("loaded", "compiled", "plain")} == {
        "loaded": 0, "compiled": 1, "plain": 0}
    assert {k: second[k] for k in ("loaded", "compiled", "plain")} == {
        "loaded": 1, "compiled": 0, "plain": 0}
    assert first["error"] < 1e-5 and second["error"] < 1e-5
