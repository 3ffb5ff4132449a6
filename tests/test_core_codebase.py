"""Habits of the codebase, checked: no import cycles in msflow, no private names imported across modules, the
public API's examples run (doctests), and a no-op import path that stays light."""

import ast
import doctest
import importlib
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import cli_env

ROOT = Path(__file__).resolve().parents[1]


def module_name(path: Path, base: Path) -> str:
    rel = path.relative_to(base).with_suffix("")
    parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
    return ".".join(parts)


def import_graph(base: Path, *packages: str) -> dict[str, set[str]]:
    """Module -> the packages' modules it imports, at any level (top of the module or inside a function)."""
    files = {module_name(f, base): f for package in packages for f in (base / package).rglob("*.py")}
    graph: dict[str, set[str]] = {}
    for name, path in files.items():
        deps = set()
        is_package = path.name == "__init__.py"
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                deps.update(a.name for a in node.names)
            elif isinstance(node, ast.ImportFrom):
                module = node.module or ""
                if node.level:
                    anchor = name if is_package else name.rpartition(".")[0]
                    for _ in range(node.level - 1):
                        anchor = anchor.rpartition(".")[0]
                    module = f"{anchor}.{module}" if module else anchor
                for alias in node.names:
                    deps.add(f"{module}.{alias.name}" if f"{module}.{alias.name}" in files else module)
        graph[name] = {d for d in deps if d in files and d != name}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        for dep in sorted(graph[node]):
            if dep not in index:
                visit(dep)
                low[node] = min(low[node], low[dep])
            elif dep in stack:
                low[node] = min(low[node], index[dep])
        if low[node] == index[node]:
            component = []
            while True:
                top = stack.pop()
                component.append(top)
                if top == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return found


def test_the_cycle_finder_finds_a_cycle_through_a_function_level_import(tmp_path):
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from pkg.b import f\n")
    (pkg / "b.py").write_text("def f():\n    from . import c\n")
    (pkg / "c.py").write_text("import pkg.a\n")
    (pkg / "d.py").write_text("import pkg.a\n")
    assert cycles(import_graph(tmp_path, "pkg")) == [["pkg.a", "pkg.b", "pkg.c"]]


def test_msflow_and_stages_have_no_import_cycles():
    graph = import_graph(ROOT, "msflow", "stages")
    assert "msflow.stores.remote" in graph and graph["msflow.api"]  # the graph is really built
    assert "stages.head.trellis" in graph and graph["stages.retarget.blend"]
    # the trellis stage's layers: segments (Eq. 10-12) <- search (Eq. 13-15) <- trellis (the stage)
    assert {"stages.head.segments", "stages.head.search"} <= graph["stages.head.trellis"]
    assert "stages.head.segments" in graph["stages.head.search"]
    assert "stages.head.trellis" not in graph["stages.head.search"]
    assert not {"stages.head.search", "stages.head.trellis"} & graph["stages.head.segments"]
    assert cycles(graph) == []
    assert not [m for m in graph if m.startswith("msflow") and any(d.startswith("stages") for d in graph[m])]


def private_imports(path: Path) -> list[str]:
    """``from m import _x``, ``import m._x``, and ``name._x`` where ``name`` was imported (a module or a class of
    another module): private names used across modules."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    imported: set[str] = set()
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            modules = [node.module or ""]
            imported.update(a.asname or a.name for a in node.names)
            found += [f"{node.lineno} imports {a.name} from {node.module}" for a in node.names if is_private(a.name)]
        elif isinstance(node, ast.Import):
            modules = [a.name for a in node.names]
            imported.update(a.asname or a.name.split(".")[0] for a in node.names)
        else:
            continue
        found += [f"{node.lineno} imports {m}" for m in modules if any(is_private(p) for p in m.split("."))]
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and is_private(node.attr):
            base = node.value
            while isinstance(base, ast.Attribute):
                base = base.value
            if isinstance(base, ast.Name) and base.id in imported:
                found.append(f"{node.lineno} uses {ast.unparse(node)}")
    return sorted(found, key=lambda line: int(line.split()[0]))


def is_private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def test_the_private_name_finder_finds_each_form(tmp_path):
    module = tmp_path / "m.py"
    module.write_text(
        "import os\nfrom a import _x, y\nimport b._c\nfrom d import E\n"
        "os._exit\nE._helper()\ny.z._w\nself_made = 1\nself_made.__class__\n"
    )
    assert private_imports(module) == [
        "2 imports _x from a",
        "3 imports b._c",
        "5 uses os._exit",
        "6 uses E._helper",
        "7 uses y.z._w",
    ]


@pytest.mark.parametrize("folder", ["msflow", "stages"])
def test_no_private_name_is_used_across_modules(folder):
    offences = [f"{p.relative_to(ROOT)}:{o}" for p in sorted((ROOT / folder).rglob("*.py")) for o in private_imports(p)]
    assert offences == []


PUBLIC_API = [
    "msflow",
    "msflow.api",
    "msflow.stage",
    "msflow.testing",
    "msflow.sinks",
    "msflow.hashing",
    "msflow.errors",
]


@pytest.mark.parametrize("module", PUBLIC_API)
def test_documented_examples_run(module):
    mod = importlib.import_module(module)
    result = doctest.testmod(mod, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert result.failed == 0


@pytest.mark.parametrize(
    "target", ["msflow.run", "msflow.Stage", "msflow.Input", "msflow.Output", "msflow.testing.run_stage"]
)
def test_public_api_has_numpydoc_sections_and_an_example(target):
    module, _, name = target.rpartition(".")
    doc = getattr(importlib.import_module(module), name).__doc__ or ""
    assert ">>>" in doc, f"{target} has no example"
    sections = [s for s in ("Parameters", "Returns", "Attributes", "Examples") if f"{s}\n    ---" in doc]
    assert "Examples" in sections and len(sections) >= 2, f"{target}: numpydoc sections {sections}"


def python_prints(code: str, cwd: Path) -> str:
    """What ``python -c code`` prints in a fresh process (which must succeed), stripped."""
    out = subprocess.run([sys.executable, "-c", code], env=cli_env(), capture_output=True, text=True, cwd=cwd)
    assert out.returncode == 0, out.stderr
    return out.stdout.strip()


def test_importing_msflow_for_a_no_op_loads_no_heavy_module():
    code = (
        "import sys, msflow, msflow.cli, msflow.api, msflow.runner; "
        "print(' '.join(m for m in ('numpy', 'zarr', 'stages', 'dask') if m in sys.modules))"
    )
    assert python_prints(code, ROOT) == ""


def test_a_local_run_that_computes_loads_no_cluster_module(numproject):
    """Running stages locally never imports Dask or distributed (0.4 s of imports a local run has no use for;
    the worker's name comes from distributed only in a process that already loaded it)."""
    code = (
        "import sys, msflow; r = msflow.run('pipeline.yaml'); assert r.ok and r.executed, r; "
        "print(' '.join(m for m in ('dask', 'distributed', 'tornado') if m in sys.modules))"
    )
    assert python_prints(code, numproject) == ""


def test_a_local_run_reads_and_writes_its_artifacts_without_zarr(numproject):
    """Stages read their inputs from a local store by decoding msflow's own chunks (msflow.stored), as they are
    written: a run imports no zarr (0.15 s) and opens no zarr group per input (about a millisecond each, most of
    what a trivial stage cost). The folders stay zarr groups: zarr reads the same values, and a lazy input's
    other attributes come from zarr."""
    code = (
        "import sys, msflow; r = msflow.run('pipeline.yaml'); assert r.ok and r.executed, r; "
        "print('zarr' in sys.modules, float(r.load('total.total')))"
    )
    assert python_prints(code, numproject).split() == ["False", "26.0"]

    import numpy as np
    import zarr

    import msflow
    from msflow.artifact import read_artifact

    result = msflow.run(numproject / "pipeline.yaml")
    folder = result.session.store.artifact_path(result.states["scaled"].key)
    view = read_artifact(folder)
    stored = view.lazy("y")
    assert type(stored._array).__name__ == "FolderArray"
    expected = np.asarray(zarr.open_group(str(folder), mode="r")["y"])
    assert np.array_equal(view["y"], expected) and view["y"].flags.writeable
    assert np.array_equal(stored[1:4], expected[1:4]) and np.array_equal(stored[::2], expected[::2])
    assert stored.shape == expected.shape and stored.nchunks == 1  # nchunks: zarr's, through the fallback
