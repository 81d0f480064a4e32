"""Dependencies point one way: scenes imports no renderer, rig imports no renderer, and
heavy libraries are imported only by the module that needs them."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
RENDERERS = {"phong_reference", "pbr_tactile"}
FORBIDDEN = {
    "scenes": RENDERERS | {"studies", "rig"},
    "rig": RENDERERS | {"studies"},
    "phong_reference": {"pbr_tactile", "studies", "rig"},
    "pbr_tactile": {"phong_reference", "studies", "rig"},
}
#: Heavy optional libraries and the only modules allowed to import them.
HEAVY = {
    "pygeodesic": {"phong_reference/geodesic.py"},
    "potpourri3d": {"phong_reference/transport.py", "scenes/elastic.py"},
    "ray": {"scenes/executors.py"},
    "serial": {"rig/serial_lines.py"},
    # the benchmark's injectors resample and filter images as the catalogue does, each its own way
    "cv2": {"rig/camera.py", "studies/gap/effects.py", "studies/gap/inject.py", "studies/gap/described.py"},
    "taxim": {"studies/compare/taxim.py"},
    "jax": {"studies/compare/taxim.py"},
}


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), str(path))
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
    return names


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_dependency_direction(package):
    for path in (ROOT / package).rglob("*.py"):
        bad = _imports(path) & FORBIDDEN[package]
        assert not bad, f"{path.relative_to(ROOT)} imports {sorted(bad)}"


def test_heavy_libraries_stay_in_their_module():
    for package in ("scenes", "phong_reference", "pbr_tactile", "rig", "studies"):
        for path in (ROOT / package).rglob("*.py"):
            rel = str(path.relative_to(ROOT))
            for lib, allowed in HEAVY.items():
                if lib in _imports(path):
                    assert rel in allowed, f"{rel} imports {lib}; only {sorted(allowed)} may"
