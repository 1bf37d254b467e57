"""The package's layout: one subpackage per pipeline stage, imports pointing one way.

The import graph is read from the source with `ast` (every `import`, also those inside
functions), so a lazy import cannot hide a cycle or an I/O dependency of the numerical core.
"""

import ast
import json
import pathlib
import subprocess
import sys

import pytest

from conftest import ROOT

SRC = ROOT / "src" / "jaxps"

# Units of the package from the bottom up: a module may import from its own unit and from the
# units before it, never from one after it. The numerical stages come first; the eager,
# file-facing ones (acquisition, report, cli) sit on top of them (docs/design.md).
LAYERS = ("core", "lights", "integration", "shading", "ps", "reflectance", "evaluate",
          "synthetic", "stability", "acquisition", "report", "cli")
NUMERICAL = frozenset(LAYERS[:LAYERS.index("acquisition")])
# What a numerical module must never import: file formats, plotting, progress bars, the CLI.
IO_PLOT_CLI = ("cv2", "PIL", "imageio", "tifffile", "colour", "skimage.io", "matplotlib",
               "tqdm", "argparse")
HEAVY = ("cv2", "matplotlib", "colour", "PIL", "tqdm", "imageio")
# Stages whose public names are all at the top level too (`jaxps.photometric_stereo`); the others
# keep theirs under their own name (`jaxps.evaluate.icp`, `jaxps.acquisition.load_capture`).
TOP_LEVEL = ("core", "lights", "integration", "shading", "ps", "reflectance")


def _module_name(path: pathlib.Path) -> str:
    parts = ("jaxps",) + path.relative_to(SRC).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _modules() -> dict[str, pathlib.Path]:
    return {_module_name(p): p for p in sorted(SRC.rglob("*.py"))}


MODULES = _modules()


def _imports(name: str, path: pathlib.Path):
    """`(imported module, line, inside a function)` for every import in the file."""
    is_package = path.name == "__init__.py"
    package = name if is_package else name.rpartition(".")[0]
    tree = ast.parse(path.read_text(encoding="utf-8"))
    functions = {id(n) for f in ast.walk(tree)
                 if isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef)) for n in ast.walk(f)}
    for node in ast.walk(tree):
        lazy = id(node) in functions
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, node.lineno, lazy
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module
            for alias in node.names:
                # `from . import synthetic` imports a module; `from .ps import PSResult` a name.
                sub = f"{target}.{alias.name}"
                yield (sub if sub in MODULES else target), node.lineno, lazy


def _unit(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[0] == "jaxps" else None


GRAPH = {name: [(m, line, lazy) for m, line, lazy in _imports(name, path)]
         for name, path in MODULES.items()}


def test_every_module_is_in_a_unit_of_the_layering():
    units = {_unit(m) for m in MODULES} - {None, "__main__"}
    assert units == set(LAYERS), units ^ set(LAYERS)


def test_no_import_cycles():
    edges = {m: sorted({t for t, _, _ in GRAPH[m] if t in MODULES and t != "jaxps"})
             for m in MODULES}
    state: dict[str, int] = {}

    def visit(m, stack):
        state[m] = 1
        for t in edges[m]:
            if state.get(t) == 1:
                cycle = stack[stack.index(t):] + [t]
                pytest.fail("import cycle: " + " -> ".join(cycle))
            if t not in state:
                visit(t, stack + [t])
        state[m] = 2

    for m in MODULES:
        if m not in state:
            visit(m, [m])


def test_imports_point_down_the_layers():
    wrong = []
    for m, imports in GRAPH.items():
        src = _unit(m)
        if src is None or src == "__main__":
            continue  # the package root re-exports everything
        for target, line, _ in imports:
            if target == "jaxps":
                wrong.append(f"{m}:{line} imports the package root")
            dst = _unit(target)
            if dst and dst != src and LAYERS.index(dst) > LAYERS.index(src):
                wrong.append(f"{m}:{line} ({src}) imports {target} ({dst})")
    assert not wrong, "\n".join(wrong)


def test_numerical_modules_import_no_io_plotting_or_cli():
    wrong = []
    for m, imports in GRAPH.items():
        unit, leaf = _unit(m), m.rsplit(".", 1)[-1]
        if unit not in NUMERICAL or leaf.startswith("_plot"):
            continue
        for target, line, _ in imports:
            is_plot_module = target.rsplit(".", 1)[-1].startswith("_plot")
            if is_plot_module and MODULES[m].name == "__init__.py":
                continue  # a package re-exports its own figures
            if target.startswith(IO_PLOT_CLI) or is_plot_module:
                wrong.append(f"{m}:{line} imports {target}")
    assert not wrong, "\n".join(wrong)


def test_plotting_modules_import_matplotlib_only_when_drawing():
    plots = [m for m in MODULES if m.rsplit(".", 1)[-1].startswith("_plot")]
    assert plots, "no plotting module found"
    for m in plots:
        eager = [t for t, _, lazy in GRAPH[m] if t.startswith("matplotlib") and not lazy]
        assert not eager, f"{m} imports matplotlib at import time"


def test_import_jaxps_is_light_and_reaches_every_subpackage():
    code = ("import json, sys, jaxps\n"
            "subs = [n for n in jaxps.__all__ if type(getattr(jaxps, n)).__name__ == 'module']\n"
            "print(json.dumps({'heavy': sorted(m for m in sys.argv[1:] if m in sys.modules),\n"
            "                  'subs': subs}))\n")
    proc = subprocess.run([sys.executable, "-c", code, *HEAVY], capture_output=True, text=True,
                          check=True, timeout=300)
    out = json.loads(proc.stdout)
    assert out["heavy"] == [], "imported by `import jaxps` before any use"
    assert set(out["subs"]) == set(LAYERS)


def test_reconstruct_command_imports_no_optimiser_or_plotting_library():
    """`jaxps reconstruct` imports its stages (acquisition, ps, integration, report) at start:
    none may pull in what only other methods use. `jaxps.ps` once imported equinox and
    optimistix for `flash_visibility`, which doubled the command's start-up."""
    heavy = (*HEAVY, "equinox", "optimistix", "lineax", "skimage", "scipy", "trimesh")
    code = ("import json, sys, jaxps.cli._reconstruct\n"
            "print(json.dumps(sorted(m for m in sys.argv[1:] if m in sys.modules)))\n")
    proc = subprocess.run([sys.executable, "-c", code, *heavy], capture_output=True, text=True,
                          check=True, timeout=300)
    assert json.loads(proc.stdout) == []


@pytest.mark.parametrize("unit", [u for u in LAYERS if (SRC / u).is_dir()])
def test_subpackage_says_what_it_takes_and_gives_and_is_reexported(unit):
    import importlib

    import jaxps

    sub = importlib.import_module(f"jaxps.{unit}")
    assert sub.__doc__ and len(sub.__doc__.strip().splitlines()) >= 3, unit
    assert sub.__all__, unit
    for name in sub.__all__:
        obj = getattr(sub, name)
        assert not name.startswith("_") and obj is not None
        if unit in TOP_LEVEL:
            assert getattr(jaxps, name, None) is obj, f"jaxps.{name} is not jaxps.{unit}.{name}"


def _main_block(tree):
    for node in tree.body:
        if (isinstance(node, ast.If) and isinstance(node.test, ast.Compare)
                and ast.unparse(node.test) == "__name__ == '__main__'"):
            return node.body
    return None


def _first_work(body):
    """The first statement of `body` (and its source) that parses the command line or calls
    anything else, leaving out the building of the parser and reads of the environment."""
    for stmt in body:
        text = ast.unparse(stmt)
        parses = "parse_args(" in text or "arguments(" in text
        if parses or (any(isinstance(n, ast.Call) for n in ast.walk(stmt))
                      and not any(k in text for k in ("ArgumentParser(", ".add_argument(",
                                                      "os.environ"))):
            return stmt, text
    return None, ""


def test_benchmark_scripts_parse_their_arguments_before_any_work():
    """`python benchmarks/X.py --help` prints usage, and an unknown option stops the script,
    before it runs (one script once ran a full benchmark on `--help` and overwrote its
    results). Checked on the source: the `__main__` block, or the module function it calls
    first, parses the command line (argparse, or `_common.arguments`) before any other call."""
    scripts = sorted((ROOT / "benchmarks").glob("*.py"))
    assert len(scripts) > 20
    late = []
    for path in scripts:
        tree = ast.parse(path.read_text())
        body = _main_block(tree)
        if body is None:
            continue
        functions = {f.name: f for f in tree.body if isinstance(f, ast.FunctionDef)}
        stmt, text = _first_work(body)
        while ("parse_args(" not in text and isinstance(stmt, ast.Expr)
               and isinstance(stmt.value, ast.Call)
               and ast.unparse(stmt.value.func) in functions):  # e.g. main(): look inside
            stmt, text = _first_work(functions.pop(ast.unparse(stmt.value.func)).body)
        if not ("parse_args(" in text or "arguments(" in text):
            late.append(f"{path.name}: first call {text[:60]!r}")
    assert not late, late
