"""Wheels that the GPU machine lacks, for Python 3.12 on manylinux x86-64, slimmed to fit its carry.

The GPU machine (``pbr_tactile.gpu_run``) has no network: what the benches import and its
image lacks travels with the working tree, 64 MiB in all, as a folder that git ignores
(default ``.whl/``). :func:`build_wheels` fills it here, where PyPI answers:

- the project itself, ``pip wheel --no-deps .`` (pure Python): the command line finds its
  subcommands through the entry points of an installed distribution, so the source tree
  on ``PYTHONPATH`` is not enough;
- every distribution in :data:`NEEDED`, each pinned to the version installed here (else
  the version in the table), ``pip download --no-deps`` for cp312 and the manylinux
  platforms of :data:`PLATFORMS`;
- the Debian packages of :data:`GL_PACKAGES` in ``gl/`` (the GL loaders, for MuJoCo's EGL
  rendering, unpacked there only when ``ldconfig`` lacks libEGL).

As downloaded they are about 100 MB (Mitsuba alone 63 MB), so each wheel is rewritten
(:func:`repack`) without the members of :data:`DROP` (Mitsuba's variants other than
``variant.FALLBACK``'s, plugins no scene of ours loads, headers, type stubs, MuJoCo's
bundled plugins and docs, ...) and with its members compressed by LZMA instead of deflate
(Python's ``zipfile`` reads both, and so pip installs both); its RECORD is written anew.
Mitsuba's ``variants()`` still names the variants left out (the list is compiled in);
setting one of them fails on import.
:data:`LEFT_OUT` says which needed distributions stay behind, and why. The folder's
``manifest.json`` lists the wheels, their sizes, the commit and what was left out.
"""

from __future__ import annotations

import base64
import csv
import hashlib
import io
import json
import os
import re
import shutil
import subprocess
import sys
import zipfile
from concurrent.futures import ProcessPoolExecutor
from importlib import metadata
from pathlib import Path

from scenes.errors import TactileSimError

from .variant import FALLBACK

#: The GPU machine's Python.
PYTHON_VERSION = "3.12"
#: Platform tags pip may take a wheel of (pip matches each exactly); the GPU machine's
#: glibc is newer than 2.28.
PLATFORMS = ("manylinux_2_28_x86_64", "manylinux_2_27_x86_64", "manylinux_2_24_x86_64", "manylinux_2_17_x86_64",
             "manylinux2014_x86_64", "manylinux1_x86_64")
#: Distributions the benches need that the GPU machine's image lacks, and the version
#: taken when none is installed here (one installed here is taken at its own version).
NEEDED = {
    "mitsuba": "3.9.1",
    "drjit": "1.5.0",
    "trimesh": "5.2.0",
    "embreex": "4.4.0.post1",  # trimesh's ray casts (the no-contact depth map): Embree
    "rtree": "1.4.1",
    "manifold3d": "3.5.4",  # the indenters' booleans
    "potpourri3d": "1.4.0",  # the elastic layer model
    "tomli-w": "1.2.0",  # writes calibration profiles
    "mujoco": "4.0.1",  # the rig's depth capture (bench dataset, calibrate --taps, rig twins)
    "mujoco-core": "4.0.1",
    "pyopengl": "3.1.10",  # MuJoCo's EGL context
    "pyserial": "3.5",  # the rig's twins (diagnose benchmark --physical)
}
#: The versions the project's ``pbr`` extra asks for: a download outside them is refused.
REQUIRED_SERIES = {"mitsuba": "3.9.", "drjit": "1.5."}
#: Runtime requirements of the project or of NEEDED that stay behind, and why.
LEFT_OUT = {
    "libigl": "13.9 MB; only scenes/curvature.py imports igl (a shape's principal curvatures, for the shape "
              "study); no bench reaches it",
    "mujoco-studio": "8.7 MB; MuJoCo's interactive studio (with mujoco-studio-wasm and websockets); neither "
                     "'import mujoco' nor its EGL renderer loads it",
    "glfw": "MuJoCo's windowed GL platform; the GPU machine renders through EGL",
    "pygeodesic": "the fast path's geodesic light field; no bench here uses it",
    "ray": "the Ray executor; the benches run locally",
    "numpy, scipy, scikit-image, matplotlib, pillow, tqdm, opencv-python-headless": "in the GPU machine's image",
}
#: Mitsuba's plugins that no scene of ours loads (shapes, emitters, materials and
#: integrators of other kinds of scene; the sky model), left out to save 31 MB unpacked.
MITSUBA_UNUSED_PLUGINS = ("bsplinecurve", "linearcurve", "ellipsoids", "ellipsoidsmesh", "sdfgrid", "hair",
                          "sunsky", "timed_sunsky", "principled", "principledthin", "measured", "measured_polarized",
                          "pplastic", "polarizer", "retarder", "stokes", "volpathmis")
#: Members left out of each distribution's wheel (regular expressions on the member's
#: path; a dist-info member is never left out).
DROP = {
    "mitsuba": (
        r"\.pyi$", r"^mitsuba/(include|cmake|pkgconfig|mitsuba_stubs)/", r"^mitsuba/mitsuba$", r"^share/",
        r"^mitsuba/data/sunsky/",
        r"^mitsuba/plugins/(" + "|".join(MITSUBA_UNUSED_PLUGINS) + r")\.so$",
        r"^mitsuba/(?!(" + "|".join(FALLBACK) + r")\.)(scalar|llvm_ad|cuda_ad)_[a-z_]+\.cpython-[^/]*\.so$",
    ),
    "drjit": (r"\.pyi$", r"^drjit/(include|cmake)/"),
    "mujoco-core": (r"^mujoco/(doc|include|plugin|sysid|testdata|usd)/", r"_test\.py$"),
    "potpourri3d": (r"^lib/.*\.a$", r"^include/"),
    "pyopengl": (r"^OpenGL/DLLS/",),
}
#: Debian packages of the GL loaders MuJoCo's EGL rendering needs on the GPU machine.
GL_PACKAGES = ("libegl1", "libglvnd0", "libopengl0", "libgl1", "libglx0", "libgles2")
#: What may travel (the working tree and the carried folder), bytes: 64 MiB less room.
CARRY_BUDGET_BYTES = 55 * 2**20
MANIFEST = "manifest.json"


class WheelError(TactileSimError, RuntimeError):
    """A wheel could not be fetched, built or rewritten."""


def normalise(name: str) -> str:
    """A distribution's name as PEP 503 compares it: ``tomli_w`` -> ``tomli-w``."""
    return re.sub(r"[-_.]+", "-", name).lower()


def pinned_versions(needed: dict[str, str] = NEEDED, installed=metadata.version) -> dict[str, tuple[str, str]]:
    """``{name: (version, where)}``: the version installed here, else the table's.

    ``where`` is "installed here" or "default". A version outside REQUIRED_SERIES raises.
    """
    out = {}
    for name, default in needed.items():
        try:
            version, where = installed(name), "installed here"
        except metadata.PackageNotFoundError:
            version, where = default, "default"
        series = REQUIRED_SERIES.get(name)
        if series and not version.startswith(series):
            raise WheelError(f"{name} {version} ({where}) is not the {series}* the reference needs")
        out[name] = (version, where)
    return out


def dropped(dist: str, member: str) -> bool:
    """Whether ``member`` (a path inside ``dist``'s wheel) is left out (DROP)."""
    if ".dist-info/" in member:
        return False
    return any(re.search(p, member) for p in DROP.get(normalise(dist), ()))


def _record_hash(data: bytes) -> str:
    return "sha256=" + base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()


def repack(source: Path, target: Path, dist: str) -> dict:
    """Rewrite wheel ``source`` as ``target``: DROP's members out, LZMA, a new RECORD.

    Returns ``{"members", "dropped", "bytes_before", "bytes"}``.
    """
    kept, n_dropped = [], 0
    with zipfile.ZipFile(source) as z:
        record = next((n for n in z.namelist() if n.endswith(".dist-info/RECORD")), None)
        if record is None:
            raise WheelError(f"{source.name} has no .dist-info/RECORD: not a wheel")
        for info in z.infolist():
            if info.is_dir() or info.filename == record:
                continue
            if dropped(dist, info.filename):
                n_dropped += 1
                continue
            kept.append((info, z.read(info)))
    rows = []
    tmp = target.with_name(target.name + ".part")
    with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_LZMA) as out:
        for info, data in kept:
            entry = zipfile.ZipInfo(info.filename, date_time=info.date_time)
            entry.external_attr = info.external_attr  # keeps the executable bit of libraries
            entry.compress_type = zipfile.ZIP_LZMA
            out.writestr(entry, data)
            rows.append((info.filename, _record_hash(data), str(len(data))))
        buf = io.StringIO()
        csv.writer(buf, lineterminator="\n").writerows(rows + [(record, "", "")])
        out.writestr(zipfile.ZipInfo(record, date_time=kept[0][0].date_time), buf.getvalue(),
                     compress_type=zipfile.ZIP_LZMA)
    tmp.replace(target)
    return {"members": len(kept), "dropped": n_dropped, "bytes_before": source.stat().st_size,
            "bytes": target.stat().st_size}


def check_wheel_dir(path: Path, repo: Path | None = None) -> Path:
    """``path`` as the wheel folder: a folder or nothing yet, and git-ignored when inside
    ``repo`` (else it would travel as untracked files and be committed)."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise ValueError(f"the wheel folder --dir {path} exists and is not a folder")
    if repo is not None:
        try:
            path.resolve().relative_to(Path(repo).resolve())
        except ValueError:
            return path
        probe = subprocess.run(["git", "-C", str(repo), "check-ignore", "-q", str(path.resolve() / "x.whl")],
                               capture_output=True)
        if probe.returncode == 1:
            raise ValueError(f"the wheel folder --dir {path} is inside the repository but not git-ignored; "
                             f"add '/{path.resolve().relative_to(Path(repo).resolve())}/' to .gitignore")
    return path


def repo_bytes(repo: Path) -> int:
    """Bytes of the tracked files and the untracked ones git does not ignore: what travels."""
    listed = subprocess.run(["git", "-C", str(repo), "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
                            capture_output=True, check=True).stdout.decode().split("\0")
    return sum(os.path.getsize(Path(repo) / p) for p in listed if p and os.path.isfile(Path(repo) / p))


def git_commit(repo: Path) -> tuple[str | None, bool | None]:
    """(HEAD's commit, whether the tree differs from it), or (None, None) outside git."""
    try:
        head = subprocess.run(["git", "-C", str(repo), "rev-parse", "HEAD"], capture_output=True, text=True,
                              check=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(repo), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, check=True).stdout.strip() != ""
    except (OSError, subprocess.CalledProcessError):
        return None, None
    return head, dirty


def _pip(*args: str) -> None:
    done = subprocess.run([sys.executable, "-m", "pip", *args], capture_output=True, text=True)
    if done.returncode != 0:
        tail = "\n".join((done.stderr or done.stdout).strip().splitlines()[-5:])
        raise WheelError(f"pip {' '.join(args[:1])} failed (exit {done.returncode}): {tail}")


def download(name: str, version: str, dest: Path) -> Path:
    """``pip download --no-deps`` of ``name==version`` for cp312 manylinux x86-64 into
    ``dest``; returns the wheel's path."""
    before = set(dest.glob("*.whl"))
    platforms = [a for p in PLATFORMS for a in ("--platform", p)]
    _pip("download", "--no-deps", "--only-binary=:all:", "--python-version", PYTHON_VERSION, "--implementation",
         "cp", *platforms, "-d", str(dest), f"{name}=={version}")
    found = [w for w in dest.glob("*.whl") if normalise(w.name.split("-")[0]) == normalise(name)]
    new = [w for w in found if w not in before] or found
    if len(new) != 1:
        raise WheelError(f"pip download {name}=={version} left {len(new)} wheels in {dest}: {[w.name for w in new]}")
    return new[0]


def download_debs(packages, dest: Path) -> list[Path]:
    """``apt-get download`` of Debian packages into ``dest`` (amd64)."""
    dest.mkdir(parents=True, exist_ok=True)
    done = subprocess.run(["apt-get", "download", "-oAPT::Architecture=amd64", *packages], cwd=dest,
                          capture_output=True, text=True)
    if done.returncode != 0:
        raise WheelError(f"apt-get download {' '.join(packages)} failed (exit {done.returncode}; run "
                         f"'apt-get update' first?): {done.stderr.strip()[-400:]}")
    return sorted(dest.glob("*.deb"))


def _repack_job(job):
    source, target, dist = job
    return repack(Path(source), Path(target), dist)


def build_wheels(dest: Path, repo: Path, gl: bool = True, workers: int = 2, log=print) -> dict:
    """Fill ``dest`` with the GPU machine's wheels (and GL loaders); returns the manifest.

    Raises ValueError for a ``dest`` that is not a folder or not git-ignored, WheelError
    when a download or build fails; a set over CARRY_BUDGET_BYTES is written all the same,
    its manifest saying so (``fits``) with the biggest wheels first.
    """
    dest = check_wheel_dir(Path(dest), repo)
    dest.mkdir(parents=True, exist_ok=True)
    for old in list(dest.glob("*.whl")) + list(dest.glob("gl/*.deb")):
        old.unlink()
    raw = dest / "downloaded"
    if raw.exists():
        shutil.rmtree(raw)
    raw.mkdir()
    try:
        pins = pinned_versions()
        jobs = []
        for name, (version, where) in pins.items():
            log(f"downloading {name}=={version} ({where})")
            wheel = download(name, version, raw)
            jobs.append((str(wheel), str(dest / wheel.name), name))
        log("building the project's wheel")
        _pip("wheel", "--no-deps", "-q", "-w", str(raw / "project"), str(repo))
        project = next((raw / "project").glob("*.whl"))
        jobs.append((str(project), str(dest / project.name), "tactile-sim"))
        log(f"rewriting {len(jobs)} wheels (LZMA, members left out per DROP)")
        with ProcessPoolExecutor(max_workers=max(1, workers)) as pool:
            stats = list(pool.map(_repack_job, jobs))
    finally:
        shutil.rmtree(raw, ignore_errors=True)
    pins["tactile-sim"] = (project.name.split("-")[1], "this tree")
    wheels = []
    for (source, target, name), stat in zip(jobs, stats):
        version, where = pins[name]
        wheels.append({"file": Path(target).name, "name": name, "version": version, "pinned_from": where, **stat})
    debs = []
    if gl:
        log(f"downloading the GL loaders ({', '.join(GL_PACKAGES)})")
        debs = [{"file": f"gl/{p.name}", "bytes": p.stat().st_size} for p in download_debs(GL_PACKAGES, dest / "gl")]
    commit, dirty = git_commit(repo)
    total = sum(w["bytes"] for w in wheels) + sum(d["bytes"] for d in debs)
    tree = repo_bytes(repo)
    manifest = {
        "python": PYTHON_VERSION, "platforms": list(PLATFORMS), "commit": commit, "dirty": dirty,
        "wheels": sorted(wheels, key=lambda w: -w["bytes"]), "gl_debs": debs, "left_out": LEFT_OUT,
        "dropped_members": {k: list(v) for k, v in DROP.items()},
        "bytes": total, "repo_bytes": tree, "carry_budget_bytes": CARRY_BUDGET_BYTES,
        "fits": total + tree <= CARRY_BUDGET_BYTES,
        "install": "python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade "
                   "--target /tmp/site .whl/*.whl && export PYTHONPATH=/tmp/site",
    }
    (dest / MANIFEST).write_text(json.dumps(manifest, indent=2) + "\n")
    return manifest
