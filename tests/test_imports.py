"""Dependencies point one way: scenes imports no renderer, rig imports no renderer, and
heavy libraries are imported only by the module that needs them. What runs follows the
imports: only the command-line layer looks a renderer up by name, and the fast path's
bakers are imported by code, not from strings."""

import ast
import functools
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
    # the benchmark's injectors resample and filter images as the catalogue does, each its own way;
    # the diagnosis registers frames with OpenCV's ECC
    "cv2": {"rig/camera.py", "studies/gap/effects.py", "studies/gap/inject_image.py", "studies/gap/described.py",
            "studies/gap/registration.py"},
    "taxim": {"studies/compare/taxim.py"},
    "jax": {"studies/compare/taxim.py"},
}


@functools.lru_cache(maxsize=None)
def _imports(path: Path) -> frozenset[str]:
    """The top-level names of the modules ``path`` imports (parsed once: the checks below
    ask again for every library)."""
    tree = ast.parse(path.read_text(), str(path))
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
    return frozenset(names)


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


# --- Renderers are chosen only by the command-line layer ----------------------------------

PACKAGES = ("scenes", "phong_reference", "pbr_tactile", "rig", "studies")
#: The registry itself, which reads the entry points.
REGISTRY = "scenes/renderers.py"
#: The command-line layer, the only code that looks a renderer up by name
#: (``scenes.renderers.get_renderer``) and passes the plugin into the code below it:
#: every module named ``cli.py`` or ``*_cli.py``, ``scenes/commands.py``, and, in any other
#: module that registers subcommands (pyproject.toml's ``tactile_sim.commands``, e.g.
#: studies/real_bench.py), its ``register`` function and its ``cmd_*`` functions.
CLI_MODULES = {"scenes/commands.py"}
#: Calls that look a renderer up by name: the registry's lookup, and
#: ``entry_points(group=...)`` of the renderers' group.
LOOKUPS = {"get_renderer"}
RENDERER_GROUP = "tactile_sim.renderers"


def _in_cli_layer(rel: str) -> bool:
    name = rel.rsplit("/", 1)[-1]
    return name == "cli.py" or name.endswith("_cli.py") or rel in CLI_MODULES


def _is_cli_function(name: str) -> bool:
    return name == "register" or name.startswith("cmd_")


def _called(node: ast.Call) -> str | None:
    func = node.func
    return func.id if isinstance(func, ast.Name) else func.attr if isinstance(func, ast.Attribute) else None


def _is_lookup(node: ast.AST) -> bool:
    if not isinstance(node, ast.Call):
        return False
    name = _called(node)
    if name in LOOKUPS:
        return True
    for keyword in node.keywords if name in ("entry_points", "select") else ():
        value = keyword.value
        if keyword.arg == "group" and (
                (isinstance(value, ast.Constant) and value.value == RENDERER_GROUP)
                or (isinstance(value, ast.Name) and value.id == "RENDERER_GROUP")
                or (isinstance(value, ast.Attribute) and value.attr == "RENDERER_GROUP")):
            return True
    return False


def renderer_lookups() -> dict[str, set[str]]:
    """Module -> the top-level functions (or classes; "<module>" for its body) that look a
    renderer up by name, outside the command-line layer and the registry."""
    found: dict[str, set[str]] = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            rel = str(path.relative_to(ROOT))
            if rel == REGISTRY or _in_cli_layer(rel):
                continue
            for top in ast.parse(path.read_text(), rel).body:
                name = getattr(top, "name", "<module>")
                if not _is_cli_function(name) and any(_is_lookup(node) for node in ast.walk(top)):
                    found.setdefault(rel, set()).add(name)
    return found


def test_only_the_command_line_layer_looks_renderers_up_by_name():
    found = {rel: sorted(names) for rel, names in renderer_lookups().items()}
    assert not found, (f"renderers looked up by name below the command-line layer: {found}; take the plugin as an "
                       "argument and let the command line choose it (scenes.renderers.get_renderer)")


def test_the_lookup_scan_sees_each_way_of_looking_up():
    tree = ast.parse("get_renderer('pbr')\nscenes.renderers.get_renderer('phong')\n"
                     "entry_points(group='tactile_sim.renderers')\nentry_points(group=RENDERER_GROUP)\n"
                     "entry_points(group='tactile_sim.commands')\nplugin.make_renderer(spec)\n")
    assert [_is_lookup(statement.value) for statement in tree.body] == [True, True, True, True, False, False]
    assert _in_cli_layer("rig/cli.py") and _in_cli_layer("pbr_tactile/calibrate_cli.py")
    assert _in_cli_layer("scenes/commands.py") and not _in_cli_layer("scenes/generate.py")
    assert _is_cli_function("register") and _is_cli_function("cmd_bench_real") and not _is_cli_function("run")


def test_bakers_are_imported_by_code_not_from_strings():
    """phong_reference/bake.py imports each light field's module in a function, so that
    the import scan above sees it; nothing there imports a module named by a string."""
    path = ROOT / "phong_reference" / "bake.py"
    tree = ast.parse(path.read_text(), str(path))
    assert "importlib" not in _imports(path)
    calls = {_called(node) for node in ast.walk(tree) if isinstance(node, ast.Call)}
    assert not calls & {"import_module", "__import__"}
    lazy = {alias.name for node in ast.walk(tree) if isinstance(node, ast.ImportFrom) and node.level == 1
            and node.module is None for alias in node.names}  # from . import linear
    assert {"linear", "plane", "geodesic", "transport"} <= lazy


def test_the_executors_run_the_tasks_they_are_given():
    """scenes.executors imports nothing of scenes.generate, which hands it its tasks
    (``scenes.generate.TASKS``): no import circle between the two."""
    path = ROOT / "scenes" / "executors.py"
    tree = ast.parse(path.read_text(), str(path))
    imported = {node.module for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)}
    imported |= {alias.name for node in ast.walk(tree) if isinstance(node, ast.Import) for alias in node.names}
    assert not imported & {"generate", "scenes.generate"}


# --- No library module imports the command-line layer --------------------------------------

#: Modules of the command-line layer besides those that register commands (pyproject.toml's
#: ``tactile_sim.commands``): the program itself and the generator of its help pages.
CLI_PROGRAM = {"scenes.cli", "scenes.docs_help"}


def _module_name(rel: str) -> str:
    """``scenes/shapes/__init__.py`` -> ``scenes.shapes``; ``rig/cli.py`` -> ``rig.cli``."""
    parts = rel[:-3].split("/")
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def cli_modules() -> set[str]:
    """The command-line layer, by module: every module that registers commands, the
    program, its help pages, and each package's ``__main__``."""
    import tomllib

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())
    registering = {value.split(":")[0] for value in project["project"]["entry-points"]["tactile_sim.commands"].values()}
    mains = {_module_name(str(p.relative_to(ROOT))) for package in PACKAGES for p in (ROOT / package).rglob("__main__.py")}
    return registering | CLI_PROGRAM | mains


def imported_modules(node: ast.AST, module: str, is_package: bool) -> set[str]:
    """The modules an import statement under ``node`` names, relative ones resolved
    against ``module``; ``from a import b`` names both ``a`` and ``a.b`` (b may be a
    submodule)."""
    names = set()
    package = module if is_package else module.rpartition(".")[0]
    for sub in ast.walk(node):
        if isinstance(sub, ast.Import):
            names |= {alias.name for alias in sub.names}
        elif isinstance(sub, ast.ImportFrom):
            base = package.split(".")[:len(package.split(".")) - (sub.level - 1)] if sub.level else []
            source = ".".join(base + ([sub.module] if sub.module else []))
            names.add(source)
            names |= {f"{source}.{alias.name}" for alias in sub.names}
    return names


def library_imports_of_the_command_line() -> dict[str, list[str]]:
    """Library module -> the command-line modules it imports (outside its own ``register``
    and ``cmd_*`` functions, which the command line calls)."""
    cli = cli_modules()
    found: dict[str, list[str]] = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            rel = str(path.relative_to(ROOT))
            module = _module_name(rel)
            if module in cli:
                continue
            for top in ast.parse(path.read_text(), rel).body:
                if _is_cli_function(getattr(top, "name", "")):
                    continue
                bad = imported_modules(top, module, path.name == "__init__.py") & cli
                if bad:
                    found.setdefault(rel, []).extend(sorted(bad))
    return found


def test_no_library_module_imports_the_command_line_layer():
    found = library_imports_of_the_command_line()
    assert not found, (f"library modules import the command-line layer: {found}; move what they need into a "
                       "library module (e.g. scenes.protocol.make_protocol, scenes.settings.name_values, "
                       "scenes.errors.REPORTED) that the command line imports too")


def test_the_command_line_scan_resolves_each_way_of_importing():
    tree = ast.parse("from . import cli\nfrom .cli import register\nfrom ..commands import x\n"
                     "import scenes.cli\nfrom scenes import commands\n")
    names = imported_modules(tree, "scenes.sub.mod", False)
    assert {"scenes.sub.cli", "scenes.commands", "scenes.cli"} <= names
    assert imported_modules(ast.parse("from .cli import run"), "studies.tiles", True) >= {"studies.tiles.cli"}
    cli = cli_modules()
    assert {"scenes.commands", "scenes.cli", "studies.real_bench", "rig.cli", "studies.tiles.cli"} <= cli
    assert "studies.sim2real.__main__" in cli and "scenes.protocol" not in cli


# --- Each package says what it offers --------------------------------------------------------

def _public_modules(package: str) -> set[str]:
    """The modules and sub-packages of ``package`` outside the command-line layer and not
    private (a leading underscore)."""
    cli = cli_modules()
    out = set()
    for path in (ROOT / package).iterdir():
        name = path.stem if path.suffix == ".py" else path.name
        if name.startswith("_") or (path.suffix != ".py" and not any(path.glob("*.py"))):
            continue
        if f"{package}.{name}" in cli or name == "cli" or name.endswith("_cli") or name == "docs_help":
            continue
        out.add(name)
    return out


@pytest.mark.parametrize("package", PACKAGES)
def test_each_package_lists_its_public_modules_and_imports_none(package):
    """Each top-level package's ``__init__`` states its concept and lists its public
    modules in ``__all__`` (a new module joins the list), and imports nothing, so that
    importing one module loads no other."""
    import importlib.util

    path = ROOT / package / "__init__.py"
    tree = ast.parse(path.read_text(), str(path))
    assert ast.get_docstring(tree), f"{package}/__init__.py has no docstring naming what the package holds"
    assert not [n for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom))], \
        f"{package}/__init__.py imports; list the modules in __all__ instead"
    listed = next(ast.literal_eval(n.value) for n in tree.body if isinstance(n, ast.Assign)
                  and any(getattr(t, "id", None) == "__all__" for t in n.targets))
    assert sorted(listed) == sorted(set(listed)), f"{package}.__all__ repeats a name"
    assert set(listed) == _public_modules(package), (
        f"{package}.__all__ differs from its public modules: missing {sorted(_public_modules(package) - set(listed))}, "
        f"extra {sorted(set(listed) - _public_modules(package))}")
    for name in listed:
        assert importlib.util.find_spec(f"{package}.{name}") is not None, f"{package}.{name} is listed but not found"


#: A module holds one concept; past this many lines it holds more (issue 75's bound).
MAX_MODULE_LINES = 600


def test_no_module_is_over_the_bound():
    long = {str(p.relative_to(ROOT)): n for package in PACKAGES for p in (ROOT / package).rglob("*.py")
            if (n := len(p.read_text().splitlines())) > MAX_MODULE_LINES}
    assert not long, f"modules over {MAX_MODULE_LINES} lines (split each by concept): {long}"
