"""The arrows go one way (docs/design.md): `meshes` → `fem` → `inverse` → `scripts`, and inside
`fem` the strategy parts `factorisation` → `tangent` → `path` → `nonlinear` → `equilibrium`.
Every import counts, a function's own too (a read of the sources, no import)."""

import ast
from pathlib import Path

import pytest

#: The tests' tier (conftest.py): no mesh, no solve.
TIER = "unit"

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ["meshes", "fem", "inverse", "scripts"]
FEM_PARTS = ["factorisation", "tangent", "path", "nonlinear", "equilibrium"]


def _imports(path: Path) -> set:
    """Dotted names of every module ``path`` imports (absolute imports)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.Import):
            names |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module)
    return names


def _package_rank(name: str):
    head = name.split(".")[0]
    return PACKAGES.index(head) if head in PACKAGES else None


def _part_rank(name: str):
    parts = name.split(".")
    if parts[0] == "fem" and len(parts) > 1 and parts[1] in FEM_PARTS:
        return FEM_PARTS.index(parts[1])
    return None


def _violations(files: list, rank) -> list:
    """(file name, imported module) where a file of rank i (``files``: (path, i)) imports a
    module of a higher rank (``rank(name)``: its rank, or None for others)."""
    return [(path.name, name) for path, i in files for name in sorted(_imports(path))
            if (rank(name) or 0) > i]


def test_packages_import_only_earlier_packages():
    files = [(p, i) for i, pkg in enumerate(PACKAGES) for p in sorted((ROOT / pkg).glob("*.py"))]
    assert len(files) > 50
    assert _violations(files, _package_rank) == []


def test_fem_strategy_parts_import_only_earlier_parts():
    files = [(ROOT / "fem" / f"{m}.py", i) for i, m in enumerate(FEM_PARTS)]
    assert _violations(files, _part_rank) == []


@pytest.mark.parametrize("rank, imported", [(_package_rank, "inverse.scene"),
                                            (_part_rank, "fem.path")])
def test_the_check_sees_a_backward_import(tmp_path, rank, imported):
    """A module of rank 1 (fem; tangent) that imports a later one inside a function is
    found: the check can fail."""
    f = tmp_path / "m.py"
    f.write_text(f"import numpy\n\n\ndef g():\n    import {imported}\n")
    assert _violations([(f, 1)], rank) == [("m.py", imported)]


def _circles(folder: Path, package: str) -> list:
    """The import circles among a package's modules (each a list of module names), every
    import counted, a function's own too."""
    from graphlib import CycleError, TopologicalSorter

    graph = {p.stem: {n.split(".")[1] for n in _imports(p)
                      if n.startswith(package + ".") and len(n.split(".")) > 1}
             for p in sorted(folder.glob("*.py"))}
    found = []
    while True:
        try:
            TopologicalSorter(graph).prepare()
            return found
        except CycleError as e:
            circle = e.args[1]
            found.append(circle)
            graph[circle[-1]].discard(circle[-2])   # drop one arrow, look for more


def test_meshes_modules_import_without_a_circle(tmp_path):
    """No circle among `meshes`' modules (anatomy, frame, landmarks and osteotomy had one,
    through a function's import of the plane and the landmark file); the check finds one."""
    assert _circles(ROOT / "meshes", "meshes") == []
    for name, body in (("a", "from meshes.b import x\n"), ("b", "def f():\n    import meshes.a\n")):
        (tmp_path / f"{name}.py").write_text(body)
    assert _circles(tmp_path, "meshes")
