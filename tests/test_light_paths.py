"""The light-path study's settings (studies.light_paths): what each run searches."""

from __future__ import annotations

import pytest

from studies import light_paths as lp


def test_a_given_grid_replaces_each_variants_own_and_keeps_its_switched_off_effects_off():
    grid = {"absorption_per_m": (5.0,), "scattering_per_m": (250.0,)}
    assert lp.variant_grid("full") == lp.VARIANTS["full"][0]
    assert lp.variant_grid("full", grid) == grid
    assert lp.variant_grid("no_scattering", grid) == {"absorption_per_m": (5.0,), "scattering_per_m": (0.0,)}
    assert lp.variant_grid("no_absorption", grid) == {"absorption_per_m": (0.0,), "scattering_per_m": (250.0,)}
    assert lp.variant_grid("guided_only", grid)["scattering_per_m"] == (0.0,)


def test_a_malformed_grid_is_refused_naming_it(capsys):
    with pytest.raises(SystemExit):
        lp.main(["--out", "unused", "--grid", "absorption_per_m=a,b"])
    assert "--grid 'absorption_per_m=a,b': expected NAME=V1,V2" in capsys.readouterr().err
