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
