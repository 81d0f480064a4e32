"""Locating the published GelTip data: $GELTIP_REFERENCE, else beside the repository."""

from __future__ import annotations

import pytest

from scenes import reference_data as rd


def test_the_environment_variable_is_the_only_place_looked_in_when_set(tmp_path, monkeypatch):
    monkeypatch.setenv(rd.REFERENCE_ENV, str(tmp_path))
    assert rd.reference_candidates() == [tmp_path]
    assert rd.reference_dir() is None
    with pytest.raises(FileNotFoundError, match=rf"not found at {tmp_path} \(set \${rd.REFERENCE_ENV}"):
        rd.require_reference_dir()
    (tmp_path / rd.MANIFEST).write_text("")
    assert rd.reference_dir() == tmp_path == rd.require_reference_dir()


def test_without_it_the_data_is_looked_for_beside_the_repository(monkeypatch):
    monkeypatch.delenv(rd.REFERENCE_ENV, raising=False)
    assert rd.reference_candidates()[0].parts[-3:] == ("shared", "data", "geltip_reference")


def test_a_given_folder_without_the_data_is_refused(tmp_path):
    with pytest.raises(FileNotFoundError, match=rf"not at {tmp_path} \(no MANIFEST.txt there\)"):
        rd.require_reference_dir(tmp_path)
    (tmp_path / "MANIFEST.txt").write_text("")
    assert rd.require_reference_dir(str(tmp_path)) == tmp_path
