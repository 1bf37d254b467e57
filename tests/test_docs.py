"""The documentation site builds with `mkdocs build --strict` (skipped without the docs extra)."""

import os
import subprocess
import sys

import pytest

from conftest import ROOT


def test_docs_build_strict(tmp_path):
    pytest.importorskip("mkdocs")
    pytest.importorskip("mkdocstrings_handlers.python")
    cmd = [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir",
           str(tmp_path / "site")]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300,
                          env={**os.environ, "NO_MKDOCS_2_WARNING": "1"})
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    for page in ("index.html", "tutorial/index.html", "evaluation/index.html",
                 "api/evaluate/index.html"):
        assert (tmp_path / "site" / page).is_file(), page
    # The tutorial pulls its code from the example that CI runs.
    assert "load_capture" in (tmp_path / "site" / "tutorial" / "index.html").read_text()
