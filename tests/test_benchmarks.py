"""The benchmark runner's bookkeeping: discovery, the JSON point contract, the Pareto front."""

import json
import sys

import pytest

from conftest import ROOT

sys.path.insert(0, str(ROOT))
runner = pytest.importorskip("benchmarks.__main__")


def _p(method, run_s, error, panel="a"):
    return {"panel": panel, "method": method, "run_s": run_s, "error": error,
            "error_name": "e", "compile_s": 0.0, "baseline": False}


def test_pareto_front_keeps_only_undominated_points():
    pts = [_p("slow-good", 10.0, 1.0), _p("fast-bad", 1.0, 5.0), _p("dominated", 12.0, 2.0),
           _p("middle", 3.0, 2.0), _p("tie", 3.5, 2.0 * (1 + 1e-5))]
    assert [p["method"] for p in runner.pareto(pts)] == ["fast-bad", "middle", "slow-good"]


def test_discover_finds_the_bench_scripts():
    topics = runner.discover()
    assert "icp" in topics
    assert all((ROOT / "benchmarks" / f"bench_{t}.py").is_file() for t in topics)


def test_points_from_results_reads_the_contract_and_skips_bad_rows():
    result = {"points": [
        {"panel": "p", "method": "m", "run_s": 0.5, "error": 2, "error_name": "deg"},
        {"panel": "p", "method": "no-time", "error": 1},
        {"panel": "p", "method": "bad", "run_s": "x", "error": 1},
    ]}
    pts = runner.points_from_results("topic", json.loads(json.dumps(result)))
    assert [(p["method"], p["run_s"], p["error"], p["source"]) for p in pts] == [
        ("m", 0.5, 2.0, "bench_topic")]
    assert runner.points_from_results("topic", {"no": "points"}) == []


def test_draw_writes_an_overview_and_one_chart_per_task(tmp_path):
    pts = [_p("a", 1e-3, 1.0, panel="PS, scene"), _p("b", 2e-3, 0.5, panel="PS, scene"),
           _p("c", 1e-3, 3.0, panel="integration, bear"), _p("d", 1e-2, 2.0, panel="mystery")]
    written = runner.draw(pts, tmp_path / "chart.png")
    assert [p.name for p in written] == ["chart.png", "chart_ps.png", "chart_integration.png",
                                         "chart_other.png"]
    assert all(p.stat().st_size > 5000 for p in written)
    assert runner.task_of("robust PS 1280x1024") == "robust"
    assert runner.task_of("relight yaleB01 cross <=30 deg") == "relight"


def _core_run(k5_ratio, ps_ns=(8.0, 8.0), peak_gb=3.5):
    """A `bench_core.py` result with the rows `benchmarks/targets.py` reads."""
    rows = [{"work": w, "impl": "jaxps", "K": k, "ratio": r} for w, k, r in [
        ("ps_l2", 5, k5_ratio), ("ps_l2", 12, 0.9), ("ps_l2_dropped", 12, 1.4), ("fc", None, 1.1),
        ("dct", None, 0.9), ("dct_solve", None, 0.5), ("ps_l2+fc", 5, 0.8)]]
    rows.append({"work": "ps_l2", "impl": "numpy pinv-matmul+normalise", "K": 5, "run_s": 0.01})
    return {"rows": rows, "peak_memory": {"peak_rss_gb": peak_gb},
            "scaling": [{"ps_l2_ns_per_px": v, "fc_ns_per_px": 10.0} for v in ps_ns]}


def test_targets_hold_every_run_to_its_bound_in_the_right_direction():
    targets = pytest.importorskip("benchmarks.targets")
    batch = {key: value for key, value in zip(targets.BATCH_ROWS.values(),
                                              [0.9, 1.0, 1.2, 1.1, 0.6, 0.5, 0.8, 0.55, 2.0],
                                              strict=True)}
    batch["batch_peak_memory"] = {"peak_rss_gb": 4.0}
    table = {r["target"]: r for r in targets.rows(
        [_core_run(0.55, (8.0, 12.0)), _core_run(0.7)], [batch], [], None, None, None)}
    k5 = table["L2 PS, K=5, 1 MP, over numpy pinv-matmul + normalise"]
    assert (k5["values"], k5["met_runs"], k5["runs"], k5["bound"]) == ([0.55, 0.7], 1, 2,
                                                                       "<= 0.6x")
    spread = table["time per pixel 0.26-16 MP, L2 PS: largest over smallest"]
    assert spread["values"] == [1.5, 1.0] and spread["met_runs"] == 1
    assert table["Frankot-Chellappa from the normals, over scipy.fft on the gradients"][
        "met_runs"] == 0
    # batches must reach the bound: 1.0x counts, 0.9x does not
    numpy_stacks = table["batch of 8 x 1 MP over 8 single calls, numpy stacks"]
    aligned = table["batch of 8 x 1 MP over 8 single calls, aligned host stacks"]
    assert (numpy_stacks["met_runs"], aligned["met_runs"], aligned["bound"]) == (0, 1, ">= 1x")
    assert "| no |" in targets.markdown([numpy_stacks]) and "| yes |" in targets.markdown(
        [aligned])
    assert "| 1 of 2 |" in targets.markdown([k5])
    # relighting: each run's `mlp` and `mlp_ratio` medians, in turn
    runs = [{"speed": {"relight": {f"relight_{m}": {"ms_median": v} for m, v in pair}}}
            for pair in ((("mlp", 5.2), ("mlp_ratio", 4.9)), (("mlp", 4.8), ("mlp_ratio", 4.6)))]
    (relight,) = targets.rows([], [], [], runs, None, None)
    assert (relight["values"], relight["met_runs"], relight["bound"]) == ([5.2, 4.9, 4.8, 4.6],
                                                                          3, "<= 5 ms")
    # the same-run ratios depend on the CPU, which each result names (bench_brdf's "machine")
    assert targets.machine({"env": {"cpu": "Xeon"}}) == "Xeon"
    assert targets.machine({"machine": {"cpu": "EPYC", "cpus": 2}}) == "EPYC"
    assert targets.machine({"machine": {"cpus": 2}}) == "not recorded"


def test_target_notes_give_the_bare_kernel_where_a_run_measured_it():
    targets = pytest.importorskip("benchmarks.targets")
    old, new = _core_run(0.7), _core_run(0.8, (8.0, 12.0))
    new["rows"] += [{"work": "ps_l2", "impl": "bare XLA kernel: normals + albedo only", "K": 5,
                     "ratio": 0.5}]
    next(r for r in new["rows"] if r["impl"] == "jaxps" and r["K"] == 5)["over_bare_kernel"] = 1.6
    for s, v in zip(new["scaling"], (4.0, 6.0), strict=True):
        s["bare_ps_ns_per_px"] = v
    table = {r["target"]: r for r in targets.rows([old, new], [], [], None, None, None)}
    note = table["L2 PS, K=5, 1 MP, over numpy pinv-matmul + normalise"]["note"]
    assert note == ("bare XLA kernel of normals and albedo over numpy, same runs: 0.50x; "
                    "jaxps over it: 1.60x")
    assert table["L2 PS, K=12, over numpy"]["note"] == ""  # no run measured it at K=12
    assert "the bare XLA kernel: 1.50x" in table[
        "time per pixel 0.26-16 MP, L2 PS: largest over smallest"]["note"]


@pytest.mark.parametrize("dropping", [False, True])
def test_bare_l2_kernel_solves_what_jaxps_solves(dropping):
    """`bench_core.py`'s bare kernel is the same solve, else its time is no floor."""
    import numpy as np

    import jaxps

    bench_core = pytest.importorskip("benchmarks.bench_core")

    k = 12 if dropping else 5
    lights = (bench_core.ring_lights(k) if dropping
              else jaxps.synthetic.scanner_lights(20.0, k=k))
    scene = jaxps.synthetic.render_scene(jaxps.synthetic.face_like(48, 40), lights)
    images = np.asarray(scene.images)
    mask = np.asarray(scene.mask)
    threshold = float(np.percentile(images[:, mask], 5)) if dropping else None
    normals, albedo = (np.asarray(a) for a in bench_core.bare_l2(lights, threshold)(images))
    ours = jaxps.photometric_stereo(images, lights, mask=mask, shadow_threshold=threshold)
    ok = np.asarray(ours.status) == 0
    assert ok.sum() > 0.5 * mask.sum()
    if dropping:
        assert (images[:, ok] < threshold).any()  # some solved pixel drops a sample
    np.testing.assert_allclose(normals[ok], np.asarray(ours.normals)[ok], atol=2e-6)
    np.testing.assert_allclose(albedo[ok], np.asarray(ours.albedo)[ok], rtol=2e-5)


def test_face_benchmarks_score_every_yale_subject_in_the_data(tmp_path, monkeypatch):
    """Subjects put beside the shared five (or in another `$JAXPS_DATA`) are scored without
    being named; with no Yale B folder the shared five are named, for the scripts' own
    message that the data is missing."""
    from benchmarks import _common

    for name in ("yaleB11", "yaleB02", "yaleB39"):
        (tmp_path / "yaleb" / name).mkdir(parents=True)
    (tmp_path / "yaleb" / "yaleB40.tar").write_bytes(b"")  # a file, not a subject
    monkeypatch.setenv("JAXPS_DATA", str(tmp_path))
    assert _common.yale_subjects() == ["yaleB02", "yaleB11", "yaleB39"]
    monkeypatch.setenv("JAXPS_DATA", str(tmp_path / "elsewhere"))
    assert _common.yale_subjects() == list(_common.SHARED_SUBJECTS)
