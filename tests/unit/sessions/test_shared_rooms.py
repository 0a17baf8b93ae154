"""SharedRooms' bookkeeping, without processes: who may join a room with which token, how many
phones it holds, and that a room whose sessions have all ended is forgotten."""

from __future__ import annotations

import pytest

from server.sessions.errors import SessionError
from server.sessions.web.live import LiveSession
from server.sessions.web.shared_rooms import SharedRooms


class _Worker:
    dropped = 0

    def post(self, method: str, *args) -> None:
        pass


def _session(sid: str) -> LiveSession:
    return LiveSession(sid, "hash", 0.0, lambda _: _Worker())


@pytest.fixture
def rooms():
    live: dict[str, LiveSession] = {sid: _session(sid) for sid in ("owner", "p2", "p3", "other")}
    shared = SharedRooms(max_phones=3, live_session=live.get)
    yield shared, live
    shared.close()


def _refused(call, code: str) -> None:
    with pytest.raises(SessionError) as err:
        call()
    assert err.value.code == code


def test_a_join_token_opens_its_own_room_only_up_to_its_phones(rooms):
    shared, live = rooms
    token = shared.invite(live["owner"])
    other_token = shared.invite(live["other"])
    assert shared.room_to_join("owner", token) is live["owner"]
    _refused(lambda: shared.room_to_join("owner", None), "unauthorized")
    _refused(lambda: shared.room_to_join("owner", other_token), "not_found")
    _refused(lambda: shared.room_to_join("nobody", token), "not_found")
    shared.joined("owner", "p2")
    shared.joined("owner", "p3")
    _refused(lambda: shared.room_to_join("owner", token), "room_full")  # 3 phones
    del live["p3"]  # a phone that left makes room again
    assert shared.room_to_join("owner", token) is live["owner"]
    _refused(lambda: shared.invite(live["p2"]), "room_unavailable")  # a joined phone
    assert shared.owner_of("p2") == "owner" and shared.phones("owner") == ["p2", "p3"]
    del live["owner"]  # the owner's session ended: its tokens open nothing
    _refused(lambda: shared.room_to_join("owner", token), "not_found")


def test_a_room_whose_sessions_have_all_ended_is_forgotten(rooms):
    shared, live = rooms
    shared.invite(live["owner"])
    shared.joined("owner", "p2")
    del live["owner"]
    shared._forget_if_over("owner")  # a phone is still in it
    assert shared.owner_of("p2") == "owner"
    del live["p2"]
    shared._forget_if_over("owner")
    assert shared.owner_of("p2") is None and shared.phones("owner") == []


def test_a_room_message_carries_each_route_cut_to_its_first_points_and_its_goal():
    import numpy as np

    from server import protocol as P
    from server.sessions.web.shared_rooms import ROOM_ROUTE_POINTS, _shortened

    long = np.arange(3 * 50, dtype=float).reshape(50, 3)
    cut = _shortened(long)
    assert len(cut) == ROOM_ROUTE_POINTS
    assert np.array_equal(cut[:-1], long[: ROOM_ROUTE_POINTS - 1]) and np.array_equal(
        cut[-1], long[-1]
    )
    assert _shortened(None) is None and _shortened(np.zeros((0, 3))) is None
    short = long[:4]
    pose = [0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    message = P.make_room(
        ["a", "b"],
        0,
        [True, True],
        ["goto", "hover"],
        [pose, pose],
        [pose, pose],
        routes=[cut, short],
    )
    decoded = P.decode(P.encode(message))
    assert decoded["route_lengths"] == [ROOM_ROUTE_POINTS, 4]
    assert np.allclose(np.reshape(decoded["routes"], (-1, 3)), np.vstack([cut, short]))
    # Without a route the fields are left out (today's message, unchanged).
    plain = P.make_room(
        ["a", "b"],
        0,
        [True, True],
        ["hover", "hover"],
        [pose, pose],
        [pose, pose],
        routes=[None, None],
    )
    assert "routes" not in plain and "route_lengths" not in plain
