"""Every script in examples/ runs (in this process, on small inputs) and writes its outputs."""

import pathlib
import runpy
import sys

import pytest

EXAMPLES = pathlib.Path(__file__).resolve().parents[1] / "examples"
# Scripts that read the shared data, and the outputs every script must leave in --out.
NEEDS_DATA = {"tutorial_yaleb.py", "icp_diligent.py"}
OUTPUTS = {
    "quickstart.py": ["quickstart_error.png"],
    "calibrate_lights.py": ["calibrate_lights.png"],
    "near_lamps.py": ["near_lamps.png"],
    "tutorial_yaleb.py": ["tutorial_yaleb.png"],
    "icp_diligent.py": ["icp_bear.png"],
    "report_demo.py": ["run/report.html", "run/report_files/normal_error_maps.png",
                       "run/report_files/scan_error_maps.png"],
}
SCRIPTS = sorted(p.name for p in EXAMPLES.glob("*.py") if not p.name.startswith("_"))


def test_every_example_is_listed():
    assert sorted(OUTPUTS) == SCRIPTS


@pytest.mark.parametrize("name", SCRIPTS)
def test_example_runs(name, tmp_path, monkeypatch, request, capsys):
    if name in NEEDS_DATA:
        request.getfixturevalue("data")  # skips when the shared data is absent
    monkeypatch.setattr(sys, "argv", [name, "--out", str(tmp_path)])
    monkeypatch.syspath_prepend(str(EXAMPLES))
    runpy.run_path(str(EXAMPLES / name), run_name="__main__")
    for out in OUTPUTS[name]:
        assert (tmp_path / out).stat().st_size > 1000, out
    assert capsys.readouterr().out.strip()  # each example reports what it found
