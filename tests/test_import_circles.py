"""No import circles: the project's modules import each other one way.

A circle held together by an import inside a function still counts: it loads only because
one side waits, and it makes each module of it depend on all the others. The graph is read
from the source (every ``import`` and ``from ... import``, at any depth of the file), at
module granularity, and its strongly connected components come from scipy's graph
routines."""

import ast
from pathlib import Path

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("scenes", "phong_reference", "pbr_tactile", "rig", "studies")


def modules(root: Path, packages=PACKAGES) -> dict[str, Path]:
    """{dotted module name: its file} of the packages under ``root``."""
    out = {}
    for package in packages:
        for path in (root / package).rglob("*.py"):
            parts = list(path.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = path
    return out


def imports_of(name: str, path: Path, known: dict[str, Path]) -> set[str]:
    """The modules of ``known`` that module ``name`` (file ``path``) imports, anywhere in
    it; ``from package import module`` names the module, not only the package."""

    def resolve(dotted: str) -> str | None:
        while dotted and dotted not in known:
            dotted = dotted.rpartition(".")[0]
        return dotted or None

    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found |= {resolve(a.name) for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                source = ".".join(base + ([node.module] if node.module else []))
            else:
                source = node.module
            found |= {resolve(f"{source}.{a.name}") for a in node.names}
    return {m for m in found if m is not None and m != name}


def circles(root: Path = ROOT, packages=PACKAGES) -> list[list[str]]:
    """Each set of modules that import each other round a circle (sorted), none when the
    imports point one way."""
    known = modules(root, packages)
    names = sorted(known)
    index = {n: i for i, n in enumerate(names)}
    edges = [(index[a], index[b]) for a in names for b in imports_of(a, known[a], known)]
    rows, cols = (np.array(v, dtype=np.int64) for v in zip(*edges)) if edges else (np.zeros(0, int),) * 2
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(len(names), len(names)))
    _, label = connected_components(graph, directed=True, connection="strong")
    groups: dict[int, list[str]] = {}
    for name, lab in zip(names, label):
        groups.setdefault(int(lab), []).append(name)
    return sorted(sorted(g) for g in groups.values() if len(g) > 1)


def test_no_import_circles():
    found = circles()
    assert not found, ("these modules import each other round a circle (imports inside functions count); move what "
                       f"they share down a layer or pass it in: {found}")


def test_a_circle_through_a_function_level_import_is_found(tmp_path):
    pkg = tmp_path / "scenes"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from scenes import b\n")
    (pkg / "b.py").write_text("def f():\n    from .c import g\n")
    (pkg / "c.py").write_text("import scenes.a\n")
    (pkg / "d.py").write_text("from scenes.a import x\n")  # imports into the circle, not part of it
    assert circles(tmp_path, ("scenes",)) == [["scenes.a", "scenes.b", "scenes.c"]]
