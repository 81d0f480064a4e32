"""The on-disk cache: hits, misses, and corrupt or stale files detected and rebuilt."""

import numpy as np
import pytest

from scenes.cache import CACHE_ENV, CacheError, cache_dir, cached, make_key, read_entry


@pytest.fixture(autouse=True)
def own_cache(tmp_path, monkeypatch):
    """Each test an empty cache of its own: these count and corrupt its entries, which the
    user's cache (or another test worker's entries in it) must not see."""
    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "cache"))


def test_cache_hit_and_rebuild_after_corruption():
    calls = []

    def build():
        calls.append(1)
        return {"a": np.arange(5.0)}

    key = make_key("x", np.ones(3))
    assert np.array_equal(cached("t", key, build)["a"], np.arange(5.0))
    assert np.array_equal(cached("t", key, build)["a"], np.arange(5.0))
    assert len(calls) == 1
    path = cache_dir() / f"t-{key}.npz"
    # Data changed behind the checksum's back.
    with np.load(path) as z:
        np.savez(path, __meta__=z["__meta__"], a=z["a"] + 1)
    with pytest.warns(UserWarning, match="checksum"):
        assert np.array_equal(cached("t", key, build)["a"], np.arange(5.0))
    assert len(calls) == 2
    # A truncated file (an interrupted copy).
    blob = path.read_bytes()
    path.write_bytes(blob[: len(blob) // 2])
    with pytest.warns(UserWarning, match="unreadable"):
        assert np.array_equal(cached("t", key, build)["a"], np.arange(5.0))
    assert len(calls) == 3
    path.write_bytes(b"")
    with pytest.warns(UserWarning):
        cached("t", key, build)
    assert len(calls) == 4


def test_stale_entries_are_detected():
    cached("t2", "k1", lambda: {"a": np.zeros(2)})
    src = cache_dir() / "t2-k1.npz"
    other = cache_dir() / "t2-k2.npz"
    other.write_bytes(src.read_bytes())
    with pytest.raises(CacheError, match="stale"):
        read_entry(other, "k2")


def test_keys_change_with_every_part():
    assert make_key("a", np.zeros(3)) != make_key("a", np.zeros(4))
    assert make_key("a", {"x": 1}) != make_key("a", {"x": 2})
    assert make_key("a", {"x": 1, "y": 2}) == make_key("a", {"y": 2, "x": 1})


def test_a_file_written_whole_or_not_at_all_keeps_the_old_one_on_an_error(tmp_path):
    from scenes.files import atomic_file, atomic_write_bytes

    path = tmp_path / "sub" / "a.bin"
    atomic_write_bytes(path, b"old")
    with pytest.raises(RuntimeError, match="killed"):
        with atomic_file(path) as fh:
            fh.write(b"half of the new")
            raise RuntimeError("killed mid-write")
    assert path.read_bytes() == b"old" and sorted(p.name for p in path.parent.iterdir()) == ["a.bin"]
