"""Atomic writes (torchheat._files): content, permissions, nothing left on failure."""

from __future__ import annotations

import os
import stat

import pytest

from torchheat._files import atomic_write, file_mode


@pytest.fixture
def umask():
    old = os.umask(0o022)
    yield
    os.umask(old)


def test_atomic_write_creates_dirs_and_gives_the_umask_permissions(tmp_path, umask):
    p = tmp_path / "a" / "b" / "out.txt"
    seen = []
    assert atomic_write(p, lambda t: seen.append(t) or t.write_text("x")) == p
    assert p.read_text() == "x"
    # written next to the destination, with its suffix (writers choosing a format by it)
    assert seen[0].parent == p.parent and seen[0].suffix == ".txt" and seen[0] != p
    assert stat.S_IMODE(p.stat().st_mode) == 0o644 == file_mode()  # not mkstemp's 0o600
    os.umask(0o007)
    atomic_write(p, lambda t: t.write_text("y"))
    assert p.read_text() == "y" and stat.S_IMODE(p.stat().st_mode) == 0o660
    assert sorted(f.name for f in p.parent.iterdir()) == ["out.txt"]


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path):
    p = tmp_path / "out.npz"
    p.write_text("old")

    def fail(t):
        t.write_text("half")
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError, match="disk full"):
        atomic_write(p, fail)
    assert p.read_text() == "old"
    assert [f.name for f in tmp_path.iterdir()] == ["out.npz"]


def test_atomic_writes_publish_together_or_not_at_all(tmp_path, umask):
    from torchheat._files import atomic_writes

    a, b = tmp_path / "map.txt", tmp_path / "pic.png"
    a.write_text("old map")
    with pytest.raises(RuntimeError, match="no picture"), atomic_writes() as out:
        out.stage(a, lambda t: t.write_text("new map"))
        out.stage(b, lambda t: (_ for _ in ()).throw(RuntimeError("no picture")))
    assert a.read_text() == "old map" and not b.exists()  # neither published
    assert sorted(f.name for f in tmp_path.iterdir()) == ["map.txt"]  # no temporaries
    with atomic_writes() as out:
        out.stage(a, lambda t: t.write_text("new map"))
        out.stage(b, lambda t: t.write_bytes(b"png"))
        assert a.read_text() == "old map" and not b.exists()  # staged, not yet published
    assert a.read_text() == "new map" and b.read_bytes() == b"png"
    assert stat.S_IMODE(b.stat().st_mode) == 0o644
