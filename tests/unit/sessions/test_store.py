"""Session files (server/sessions/store.py): a restarted server cleans the partial files of an
interrupted write only once no process of the run before still writes there."""

from __future__ import annotations

import os

from server.sessions.store import SessionStore, hold_writers_lock
from server.sessions.web.manager import SessionManager


def _killed_mid_snapshot(store: SessionStore, sid: str) -> None:
    """A session's folder as a server killed while it snapshotted leaves it."""
    store.write_meta(sid, {"id": sid, "token_sha256": "0" * 64, "created_at": 0.0, "status": {}})
    (store.staging(sid) / "map.ply").write_bytes(b"half")
    (store.folder(sid) / ".map.npz.tmp123.npz").write_bytes(b"half")


def test_the_partial_files_are_removed_once_no_earlier_process_writes(tmp_path):
    store = SessionStore(tmp_path)
    sid = "0123456789abcdef"
    _killed_mid_snapshot(store, sid)
    writer = hold_writers_lock(tmp_path)  # a session process of the killed server, still writing
    try:
        assert not store.wait_for_writers(0.2)
        manager = SessionManager(store)
        assert manager.load_saved(writers_timeout_s=0.2) == 1  # indexed, not cleaned
        assert (store.folder(sid) / ".snapshot").is_dir()
    finally:
        os.close(writer)  # it ended
    assert store.wait_for_writers(0.2)
    assert SessionManager(store).load_saved(writers_timeout_s=0.2) == 1
    assert sorted(p.name for p in store.folder(sid).iterdir()) == ["meta.json"]


def test_writers_share_the_lock(tmp_path):
    first, second = hold_writers_lock(tmp_path), hold_writers_lock(tmp_path)
    os.close(first)
    assert not SessionStore(tmp_path).wait_for_writers(0.1)
    os.close(second)
    assert SessionStore(tmp_path).wait_for_writers(0.1)
