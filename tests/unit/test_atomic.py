"""The one atomic write: whole new content, or the old content and no leftover on failure."""

from __future__ import annotations

import stat
from pathlib import Path

import pytest

from server.atomic import atomic_write, atomic_write_bytes


def test_writes_whole_file_private_by_default(tmp_path):
    path = tmp_path / "sub" / "key.pem"
    atomic_write_bytes(path, b"secret")
    assert path.read_bytes() == b"secret"
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert [p.name for p in path.parent.iterdir()] == ["key.pem"]


def test_mode_and_suffix_reach_the_writer(tmp_path):
    path = tmp_path / "map.ply"
    seen = []

    def write(tmp: str) -> None:
        seen.append(tmp)
        Path(tmp).write_text("ply")

    atomic_write(path, write, suffix=".ply", mode=0o644)
    assert seen[0].endswith(".ply") and Path(seen[0]).parent == tmp_path
    assert path.read_text() == "ply"
    assert stat.S_IMODE(path.stat().st_mode) == 0o644


def test_failure_keeps_old_content_and_leaves_no_temp_file(tmp_path):
    path = tmp_path / "trajectory.tum"
    path.write_text("old\n")

    def half_then_fail(tmp: str) -> None:
        Path(tmp).write_text("half")
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError, match="disk full"):
        atomic_write(path, half_then_fail, durable=True)
    assert path.read_text() == "old\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["trajectory.tum"]
