"""The documentation site builds with `mkdocs build --strict` (skipped without the docs extra)."""

import os
import re
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
    for page in ("index.html", "tutorial/index.html", "evaluation/index.html", "design/index.html",
                 "api/evaluate/index.html", "api/ps/index.html", "api/acquisition/index.html"):
        assert (tmp_path / "site" / page).is_file(), page
    # The tutorial pulls its code from the example that CI runs.
    assert "load_capture" in (tmp_path / "site" / "tutorial" / "index.html").read_text()

    # Offline: formulas are MathML made at build time, and no page loads a remote script,
    # stylesheet or font.
    pages = {p: p.read_text() for p in (tmp_path / "site").rglob("*.html")}
    for path, text in pages.items():
        remote = re.findall(r'<(?:script|link)[^>]*(?:src|href)="(?:https?:)?//[^"]*"[^>]*>', text)
        assert not [r for r in remote if "<script" in r or "stylesheet" in r], (path, remote)
        assert not re.search(r'class="arithmatex">\s*\\[(\[]', text), f"raw TeX in {path}"
    ps = pages[tmp_path / "site" / "photometric_stereo" / "index.html"]
    assert ps.count('<span class="arithmatex"><math') >= 5
    assert not (tmp_path / "site" / "hooks").exists()


def test_every_subpackage_has_an_api_page_in_the_nav():
    """The API reference follows the package layout: one page per subpackage, all in the nav."""
    import types

    import jaxps

    nav = (ROOT / "mkdocs.yml").read_text()
    subs = [n for n in jaxps.__all__ if isinstance(getattr(jaxps, n), types.ModuleType)]
    assert {"acquisition", "ps", "integration", "reflectance", "evaluate", "cli"} <= set(subs)
    for name in subs:
        page = ROOT / "docs" / "api" / f"{name}.md"
        assert page.is_file(), page
        assert f"::: jaxps.{name}" in page.read_text(), page
        assert f"api/{name}.md" in nav, name
    # The design notes name every folder of src/jaxps.
    design = (ROOT / "docs" / "design.md").read_text()
    folders = [p.name for p in (ROOT / "src" / "jaxps").iterdir()
               if p.is_dir() and (p / "__init__.py").is_file()]
    assert folders and all(f"`{f}/`" in design for f in folders), folders
