"""Every error the project raises on purpose derives from scenes.errors.TactileSimError,
so that the command line reports it in one line instead of a traceback."""

import ast
import builtins
import importlib
from pathlib import Path

import pytest

from scenes.errors import TactileSimError

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("scenes", "rig", "pbr_tactile", "phong_reference", "studies")
#: Builtin exception classes, by name: a class deriving from one of them is an error class.
BUILTIN_ERRORS = {name for name, value in vars(builtins).items()
                  if isinstance(value, type) and issubclass(value, BaseException) and not issubclass(value, Warning)}


def _error_classes() -> list[tuple[str, str]]:
    """(module, class) of every class in the packages that derives from an exception:
    a builtin one, or a base named like one (``...Error``, ``...Aborted``, ``...Timeout``)."""
    found = []
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            module = ".".join(path.relative_to(ROOT).with_suffix("").parts)
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if not isinstance(node, ast.ClassDef):
                    continue
                bases = {b.attr if isinstance(b, ast.Attribute) else getattr(b, "id", "") for b in node.bases}
                if bases & BUILTIN_ERRORS or any(b.endswith(("Error", "Exception", "Aborted", "Timeout"))
                                                 for b in bases):
                    found.append((module, node.name))
    return found


ERROR_CLASSES = _error_classes()


def test_the_scan_finds_the_known_errors():
    names = {name for _, name in ERROR_CLASSES}
    assert {"PrinterError", "PrinterTimeout", "ServoError", "ServoTimeout", "CameraError", "SessionAborted",
            "EnvelopeError", "VariantError", "GLPlatformError", "DatasetError", "CacheError"} <= names


@pytest.mark.parametrize("module, name", ERROR_CLASSES, ids=[name for _, name in ERROR_CLASSES])
def test_each_error_class_is_a_tactile_sim_error(module, name):
    cls = getattr(importlib.import_module(module), name)
    assert issubclass(cls, TactileSimError), f"{module}.{name} bases {[b.__name__ for b in cls.__bases__]}"


@pytest.mark.parametrize("module, name, builtin", [
    ("rig.marlin", "PrinterError", RuntimeError), ("rig.servos", "ServoError", RuntimeError),
    ("rig.camera", "CameraError", RuntimeError), ("rig.session", "SessionAborted", RuntimeError),
    ("rig.envelope", "EnvelopeError", ValueError), ("pbr_tactile.variant", "VariantError", RuntimeError),
    ("scenes.gl", "GLPlatformError", RuntimeError), ("scenes.dataset", "DatasetError", ValueError),
    ("scenes.cache", "CacheError", ValueError),
])
def test_error_classes_keep_their_builtin_base(module, name, builtin):
    """Existing ``except RuntimeError`` / ``except ValueError`` clauses still catch them."""
    assert issubclass(getattr(importlib.import_module(module), name), builtin)
