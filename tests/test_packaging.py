"""Packaging: the wheel built from this repository, installed non-editable, works alone.

The wheel is built from a copy of the files git would commit (so neither a stale
``build/`` nor untracked output gets in), installed with ``pip --target`` into a bare
folder, and run from a folder outside the repository with ``PYTHONPATH`` naming only
that folder. What it must hold is read off the source tree, never listed by hand:
every folder with an ``__init__.py`` under each top-level package, and every other file
there (the sensor specs, the servo board's sketch).
"""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import subprocess
import sys
import tomllib
import zipfile
from dataclasses import dataclass
from importlib.metadata import version
from pathlib import Path, PurePosixPath

import pytest

from scenes.spec import DEFAULT_SPEC_PATH

REPO = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((REPO / "pyproject.toml").read_text())
#: Seconds that building or installing the wheel may take (pip may fetch build requirements).
BUILD_TIMEOUT_S = 300
#: Seconds that each command of the installed wheel may take.
COMMAND_TIMEOUT_S = 300
#: setuptools writes wheels without the ``wheel`` package from this version on.
SETUPTOOLS_OWN_BDIST_WHEEL = (70, 1)

#: One cheap, real command of each top-level package, run through the installed
#: ``tactile-sim`` entry point: (arguments, a file it must write or a line it must print,
#: the optional library it needs).
COMMANDS = {
    "scenes": (["scene", "export", "--object", "sphere", "-o", "rig_xml"], "rig_xml/rig.xml", None),
    "phong_reference": (["bake", "--field", "linear"], "valid 100.0% of the image circle", None),
    "pbr_tactile": (["reference", "--indenter", "sphere", "--at", "320,240", "--depth-mm", "1", "--width", "8",
                     "--height", "6", "--passes", "2", "--spp", "2", "--estimator", "volpath", "--out", "frame"],
                    "frame.npy", "mitsuba"),
    "rig": (["rig", "run", "--dry-run", "--limit", "2", "--out", "capture"], "nothing was sent", "serial"),
    "studies": (["design", "--sweep", "led_height=0.01", "--taps", "1", "--no-reference", "--field", "linear",
                 "--quiet", "--out", "design"], "design/design.json", None),
}
#: Packages whose command renders (10 to 30 s on 2 busy cores): marked slow.
RENDERING = {"pbr_tactile", "studies"}

#: Run in the installed wheel: imports every module it holds and loads every entry point,
#: and prints where each came from (JSON). A module may fail only for want of an optional
#: library outside the wheel.
IMPORT_ALL = """
import importlib, json, pkgutil, sys
from importlib.metadata import distribution, entry_points
from types import ModuleType

tops, groups = json.loads(sys.argv[1]), json.loads(sys.argv[2])
modules, missing = {}, {}
for top in tops:
    package = importlib.import_module(top)
    modules[top] = package.__file__
    for info in pkgutil.walk_packages(package.__path__, top + "."):
        try:
            module = importlib.import_module(info.name)
        except ModuleNotFoundError as exc:
            if (exc.name or "").split(".")[0] in tops:
                raise
            missing[info.name] = exc.name
            continue
        modules[info.name] = getattr(module, "__file__", None) or list(module.__path__)[0]
points = {}
for group in groups:
    for ep in entry_points(group=group):
        loaded = ep.load()
        module = loaded if isinstance(loaded, ModuleType) else sys.modules[loaded.__module__]
        points.setdefault(group, {})[ep.name] = [module.__name__, module.__file__]
print(json.dumps({"dist": str(distribution("tactile-sim").locate_file("")), "modules": modules,
                  "missing": missing, "entry_points": points}))
"""

#: Run in the installed wheel: ``tactile-sim ARGS`` through its console-script entry
#: point, then a check that every module of the project it loaded came from the wheel.
RUN_COMMAND = """
import sys
from importlib.metadata import entry_points
from pathlib import Path

site, tops = Path(sys.argv[1]).resolve(), sys.argv[2].split(",")
(main,) = [ep.load() for ep in entry_points(group="console_scripts", name="tactile-sim")]
code = main(sys.argv[3:])
stray = sorted(name for name, module in list(sys.modules.items())
               if name.split(".")[0] in tops and getattr(module, "__file__", None)
               and site not in Path(module.__file__).resolve().parents)
if stray:
    sys.exit(f"modules loaded from outside the installed wheel: {stray}")
sys.exit(code)
"""


@dataclass(frozen=True)
class Installed:
    """The wheel built from the repository and the folder it was installed into."""

    wheel: Path
    site: Path  # pip install --target: the wheel's packages, its dist-info and bin/
    root: Path  # a scratch folder outside the repository
    sources: tuple[PurePosixPath, ...]  # the repository's files, relative to it


def repository_files() -> list[PurePosixPath]:
    """The files git would commit (tracked or new, not ignored) that exist now."""
    if shutil.which("git") is None:
        pytest.skip("git is not installed: the repository's files cannot be told from build outputs")
    listed = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=REPO,
                            capture_output=True, text=True)
    if listed.returncode != 0:
        pytest.skip(f"{REPO} is not a git checkout: {listed.stderr.strip()}")
    return sorted({PurePosixPath(p) for p in listed.stdout.split("\0") if p and (REPO / p).is_file()})


def top_level_packages(files) -> list[str]:
    """Folders at the repository's root that hold an ``__init__.py``."""
    return sorted(f.parts[0] for f in files if len(f.parts) == 2 and f.name == "__init__.py")


def regular_packages(files) -> list[str]:
    """Dotted names of every folder with an ``__init__.py`` under a top-level package."""
    tops = set(top_level_packages(files))
    return sorted(".".join(f.parent.parts) for f in files if f.name == "__init__.py" and f.parts[0] in tops)


def data_files(files) -> list[PurePosixPath]:
    """Files under the top-level packages that are not Python modules."""
    tops = set(top_level_packages(files))
    return [f for f in files if f.parts[0] in tops and len(f.parts) > 1 and f.suffix != ".py"]


def build_isolation_flags() -> list[str]:
    """``--no-build-isolation`` where this Python can build the wheel itself, else nothing.

    Building without isolation needs the project's build requirements installed and a
    setuptools that writes wheels; otherwise pip fetches them into an isolated
    environment from its index.
    """
    from packaging.requirements import Requirement
    from packaging.version import Version

    for text in PYPROJECT["build-system"]["requires"]:
        requirement = Requirement(text)
        if importlib.util.find_spec(requirement.name) is None:
            return []
        if not requirement.specifier.contains(version(requirement.name), prereleases=True):
            return []
    own = Version(version("setuptools")).release[:2] >= SETUPTOOLS_OWN_BDIST_WHEEL
    return ["--no-build-isolation"] if own or importlib.util.find_spec("wheel") else []


def pip(*args: str) -> None:
    """Run pip quietly; fail with its output when it fails."""
    done = subprocess.run([sys.executable, "-m", "pip", "--disable-pip-version-check", *args],
                          capture_output=True, text=True, timeout=BUILD_TIMEOUT_S)
    assert done.returncode == 0, f"pip {' '.join(args)} failed:\n{done.stdout[-4000:]}\n{done.stderr[-4000:]}"


def installed_env(installed: Installed) -> dict[str, str]:
    """The environment of a process that sees the installed wheel and not the repository."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTHON")}
    return {**env, "PYTHONPATH": str(installed.site), "PYTHONNOUSERSITE": "1",
            "TACTILE_SIM_CACHE": str(installed.root / "cache")}


def run_installed(installed: Installed, code: str, *args: str, cwd: Path) -> subprocess.CompletedProcess:
    cwd.mkdir(parents=True, exist_ok=True)
    return subprocess.run([sys.executable, "-c", code, *args], cwd=cwd, env=installed_env(installed),
                          capture_output=True, text=True, timeout=COMMAND_TIMEOUT_S)


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> Installed:
    """Build the wheel from a copy of the repository's files and install it non-editable."""
    files = repository_files()
    root = tmp_path_factory.mktemp("packaging")
    source = root / "source"
    for f in files:
        (source / f).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(REPO / f, source / f)
    pip("wheel", "--no-deps", *build_isolation_flags(), "-w", str(root / "dist"), str(source))
    (wheel,) = (root / "dist").glob("*.whl")
    pip("install", "--no-deps", "--no-compile", "--target", str(root / "site"), str(wheel))
    return Installed(wheel=wheel, site=root / "site", root=root, sources=tuple(files))


def test_the_source_tree_has_the_packages_the_tests_know():
    files = repository_files()
    assert set(top_level_packages(files)) == set(COMMANDS), "give each top-level package a command in COMMANDS"
    assert "tests" not in top_level_packages(files)


def test_the_wheel_holds_every_package_and_data_file_of_the_tree(installed):
    names = set(zipfile.ZipFile(installed.wheel).namelist())
    packages = regular_packages(installed.sources)
    missing = [p for p in packages if p.replace(".", "/") + "/__init__.py" not in names]
    assert not missing, f"packages of the source tree missing from {installed.wheel.name}: {missing}"
    data = data_files(installed.sources)
    assert str(PurePosixPath(DEFAULT_SPEC_PATH.resolve().relative_to(REPO))) in {str(f) for f in data}
    missing = [str(f) for f in data if str(f) not in names]
    assert not missing, f"data files of the source tree missing from {installed.wheel.name}: {missing}"
    tops = set(top_level_packages(installed.sources))
    strays = sorted(n for n in names if n.split("/")[0] not in tops and ".dist-info/" not in n)
    assert not strays, f"files outside the project's packages in {installed.wheel.name}: {strays}"


def test_every_module_and_entry_point_imports_from_the_installed_wheel(installed):
    tops = top_level_packages(installed.sources)
    groups = sorted(PYPROJECT["project"]["entry-points"])
    done = run_installed(installed, IMPORT_ALL, json.dumps(tops), json.dumps(groups), cwd=installed.root / "imports")
    assert done.returncode == 0, done.stderr[-4000:]
    found = json.loads(done.stdout.splitlines()[-1])
    site = installed.site.resolve()
    assert Path(found["dist"]).resolve() == site, "tactile-sim's metadata came from elsewhere"
    outside = {name: f for name, f in found["modules"].items() if site not in Path(f).resolve().parents}
    assert not outside, f"imported from outside the installed wheel: {outside}"
    assert set(regular_packages(installed.sources)) <= set(found["modules"])
    expected_modules = {str(f.with_suffix("")).replace("/", ".") for f in installed.sources
                        if f.suffix == ".py" and f.parts[0] in tops}
    expected_modules = {m.removesuffix(".__init__") for m in expected_modules}
    assert expected_modules == set(found["modules"]) | set(found["missing"])
    for group in groups:
        declared = PYPROJECT["project"]["entry-points"][group]
        assert set(found["entry_points"].get(group, {})) == set(declared), group
        for name, (module, path) in found["entry_points"][group].items():
            assert module == declared[name].split(":")[0], f"{group} {name} loaded {module}"
            assert site in Path(path).resolve().parents, f"{group} {name} loaded {path}"


@pytest.mark.parametrize("package", [pytest.param(p, marks=pytest.mark.slow) if p in RENDERING else p
                                     for p in sorted(COMMANDS)])
def test_one_command_of_each_package_runs_from_the_installed_wheel(installed, package):
    args, expected, needs = COMMANDS[package]
    if needs is not None and importlib.util.find_spec(needs) is None:
        pytest.skip(f"{package}'s command needs {needs}, which is not installed")
    work = installed.root / "commands" / package
    tops = ",".join(top_level_packages(installed.sources))
    done = run_installed(installed, RUN_COMMAND, str(installed.site), tops, *args, cwd=work)
    assert done.returncode == 0, f"tactile-sim {' '.join(args)}:\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
    said = done.stdout + done.stderr
    assert (work / expected).is_file() or expected in said, f"{' '.join(args)}: no {expected}:\n{said[-3000:]}"
