"""Locate the authors' published GelTip data (read in place, never shipped with the project).

The data is looked for in ``$GELTIP_REFERENCE`` when that is set (and only there: an
explicit location is never second-guessed), else in ``shared/data/geltip_reference``
beside the repository, then beside the working directory. A folder holds the data when
it has the data's ``MANIFEST.txt``.
"""

from __future__ import annotations

import os
from pathlib import Path

#: Environment variable naming the folder of the published data.
REFERENCE_ENV = "GELTIP_REFERENCE"
#: The folder's path below a directory that sits beside the repository.
SIBLING = Path("shared") / "data" / "geltip_reference"
#: The file that marks a folder as the published data.
MANIFEST = "MANIFEST.txt"
#: Per pixel, two no-contact frames of the published GelTip's camera differ by about this
#: much (RGB, [0, 1] display units): the noise floor of any sim-to-real comparison, and
#: the least image change a real camera shows (``studies.design``).
CAMERA_NOISE_RGB = (0.012, 0.010, 0.006)


def reference_candidates() -> list[Path]:
    """Where the data is looked for, in order."""
    given = os.environ.get(REFERENCE_ENV)
    if given:
        return [Path(given)]
    beside_repo = Path(__file__).resolve().parents[2] / SIBLING
    beside_cwd = Path.cwd().parent / SIBLING
    return [beside_repo] if beside_cwd == beside_repo else [beside_repo, beside_cwd]


def reference_dir() -> Path | None:
    """The published data's folder, or None when no candidate holds it
    (``require_reference_dir`` says why)."""
    return next((c for c in reference_candidates() if (c / MANIFEST).is_file()), None)


def require_reference_dir(path: Path | str | None = None) -> Path:
    """The published data's folder: ``path`` checked, or (None) the one found.

    Raises FileNotFoundError naming where it looked and how to point at the data.
    """
    if path is not None:
        path = Path(path)
        if not (path / MANIFEST).is_file():
            raise FileNotFoundError(f"the GelTip reference data is not at {path} (no {MANIFEST} there)")
        return path
    found = reference_dir()
    if found is None:
        where = ", ".join(str(c) for c in reference_candidates())
        raise FileNotFoundError(f"GelTip reference data not found at {where} (set ${REFERENCE_ENV} to its folder)")
    return found


#: The real GelTip contacts cut from the paper's figure, below the published data's folder.
REAL_CONTACTS = "real_contacts"


def require_real_contacts_dir(path: Path | str | None = None) -> Path:
    """The folder of the figure's real contacts (``real_contacts/README.md``): ``path``
    checked, or (None) ``real_contacts`` in the published data's folder.

    Raises FileNotFoundError naming the path that is not a folder, or where the published
    data was looked for.
    """
    folder = Path(path) if path is not None else require_reference_dir() / REAL_CONTACTS
    if not folder.is_dir():
        raise FileNotFoundError(f"the GelTip figure's real contacts are not at {folder} (no such folder)")
    return folder


#: The public GelSight ball presses (Taxim's calibration set): their folder below a
#: directory beside the repository, the environment variable naming it elsewhere, and
#: the archive in it.
TAXIM_SIBLING = Path("shared") / "data" / "real_gelsight_taxim"
TAXIM_ENV = "REAL_GELSIGHT_TAXIM"
TAXIM_ARCHIVE = "dataPack_small.npz"


def require_taxim_archive() -> Path:
    """The public GelSight presses' archive: in ``$REAL_GELSIGHT_TAXIM`` when that is set,
    else beside the repository (as the GelTip data is looked for). FileNotFoundError naming
    where it looked otherwise."""
    given = os.environ.get(TAXIM_ENV)
    candidates = [Path(given)] if given else [Path(__file__).resolve().parents[2] / TAXIM_SIBLING,
                                              Path.cwd().parent / TAXIM_SIBLING]
    for folder in candidates:
        if (folder / TAXIM_ARCHIVE).is_file():
            return folder / TAXIM_ARCHIVE
    raise FileNotFoundError(f"the public GelSight ball presses ({TAXIM_ARCHIVE}) are not at "
                            f"{', '.join(map(str, candidates))} (set ${TAXIM_ENV} to their folder, or pass --archive)")
