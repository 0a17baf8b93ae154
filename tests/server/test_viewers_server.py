"""Viewer links through the real server: a second phone watches a session live, read-only (a slow
viewer's outbox: tests/unit/transport/test_viewers.py)."""

from __future__ import annotations

import asyncio

import httpx
import numpy as np
import websockets

from server import protocol as proto
from server.datasets import open_dataset
from server.transport.schemas import ViewerCreated, ViewerList
from tests.conftest import auth
from tests.server.test_drone_server import Pilot
from tests.server.test_openapi_server import strictly

FRAMES = 24


class Viewer(Pilot):
    """A viewer's socket: keeps every message, and the close code when the server closes it."""

    @classmethod
    async def open(cls, url: str, **kwargs) -> Viewer:
        viewer = cls(await websockets.connect(url, max_size=None, **kwargs))
        viewer.task = asyncio.create_task(viewer.receive_all())
        return viewer

    async def receive_all(self) -> None:
        try:
            await self.receive()
        except websockets.ConnectionClosed:
            pass

    async def closed_with(self, timeout: float = 10.0) -> int | None:
        await asyncio.wait_for(self.task, timeout)
        return self.ws.close_code


async def _watch(server, dataset) -> dict:
    sid, token = server.create_session()
    K = dataset.intrinsics
    out: dict = {}
    async with httpx.AsyncClient(base_url=server.url) as rest:
        assert (await rest.post(f"/api/sessions/{sid}/viewers")).status_code == 401
        stranger = await rest.post(f"/api/sessions/{sid}/viewers", headers=auth("x" * 43))
        assert stranger.status_code == 404
        link = (await rest.post(f"/api/sessions/{sid}/viewers", headers=auth(token))).json()
        other = (await rest.post(f"/api/sessions/{sid}/viewers", headers=auth(token))).json()
        strictly(ViewerCreated, link)
        out["link"] = link
        owner = Pilot(
            await websockets.connect(
                f"{server.ws_url}/ws/sessions/{sid}?token={token}", max_size=None
            )
        )
        owner_task = asyncio.create_task(owner.receive())
        await owner.send(proto.make_hello("owner", (K.fx, K.fy, K.cx, K.cy), (K.width, K.height)))
        await owner.wait_for("welcome")
        half = FRAMES // 2
        for i in range(half):
            frame = dataset[i]
            await owner.send(proto.make_frame(i, frame.timestamp, frame.colour, frame.depth))
            await owner.wait_for("pose", seq=i)
        await owner.wait_for("drone_event", timeout=30.0, event="spawned")

        # Two viewers join mid-session, and one that never reads its socket.
        view_url = f"{link['websocket']}?token={link['viewer_token']}"
        viewer = await Viewer.open(view_url)
        second = await Viewer.open(f"{other['websocket']}?token={other['viewer_token']}")
        stuck = await websockets.connect(view_url, max_size=None, max_queue=1)
        out["welcome"] = await viewer.wait_for("welcome")
        out["backlog_spawned"] = await viewer.wait_for("drone_event", event="spawned")
        await viewer.wait_for("map_chunk")
        # A viewer's token is not the owner's: on the owner's socket it opens nothing, and
        # takes nothing over.
        intruder = await Viewer.open(
            f"{server.ws_url}/ws/sessions/{sid}?token={link['viewer_token']}"
        )
        out["intruder_close"] = await intruder.closed_with()
        out["intruder_error"] = intruder.of("error")

        # The owner streams on; the viewers see it live.
        for i in range(half, FRAMES):
            frame = dataset[i]
            await owner.send(proto.make_frame(i, frame.timestamp, frame.colour, frame.depth))
            await owner.wait_for("pose", seq=i)
        await viewer.wait_for("pose", seq=FRAMES - 1)
        await second.wait_for("pose", seq=FRAMES - 1)

        # The viewer tries to fly the drone and to send a frame: refused, nothing changes.
        before = owner.of("drone_state")[-1]
        poses = {m["seq"]: proto.pose_matrix(m) for m in owner.of("pose")}
        target = poses[half][:3, 3] + 0.7 * poses[half][:3, 2]
        await viewer.send(proto.make_command(77, "goto", target=target))
        await viewer.send(proto.make_command(78, "land"))
        frame = dataset[0]
        await viewer.send(proto.make_frame(999, frame.timestamp, frame.colour, frame.depth))
        out["refused"] = [
            await viewer.wait_for("error", command_id=77),
            await viewer.wait_for("error", command_id=78),
            await viewer.wait_for("error", seq=999),
        ]
        await asyncio.sleep(1.0)
        out["owner_states_after"] = owner.of("drone_state")[owner.of("drone_state").index(before) :]
        out["owner_errors"] = owner.of("error")
        out["owner_poses"] = len(owner.of("pose"))

        # The owner still commands; the viewers see its command's states.
        await owner.send(proto.make_command(5, "land"))
        out["viewer_landing"] = await viewer.wait_for("drone_state", timeout=10.0, command_id=5)
        out["viewer"] = viewer.messages
        out["second"] = second.messages

        # Revoking one link closes its sockets (the stuck one too) and only those.
        listed = (await rest.get(f"/api/sessions/{sid}/viewers", headers=auth(token))).json()
        strictly(ViewerList, listed)
        out["listed"] = listed["viewers"]
        revoke = await rest.delete(
            f"/api/sessions/{sid}/viewers/{link['viewer_id']}", headers=auth(token)
        )
        out["revoke_status"] = revoke.status_code
        out["revoked_close"] = await viewer.closed_with()
        out["revoked_error"] = viewer.of("error")[-1]
        again = await Viewer.open(view_url)
        out["again_close"] = await again.closed_with()
        unknown = await rest.delete(
            f"/api/sessions/{sid}/viewers/{link['viewer_id']}", headers=auth(token)
        )
        out["unknown_revoke"] = unknown.status_code
        states = len(second.of("drone_state"))
        await asyncio.sleep(0.5)
        out["second_still_watching"] = len(second.of("drone_state")) > states
        await stuck.close()

        await owner.send(proto.make_bye())
        await asyncio.wait_for(owner_task, 10)
        # The session's end ends its viewers.
        assert (await rest.delete(f"/api/sessions/{sid}", headers=auth(token))).status_code == 204
        out["deleted_close"] = await second.closed_with()
    return out


def test_a_viewer_watches_live_cannot_command_and_is_closed_when_revoked(live_server, shared_data):
    dataset = open_dataset(shared_data / "synthetic_room0")
    server = live_server()
    out = asyncio.run(_watch(server, dataset))

    link = out["link"]
    assert link["url"].endswith(
        f"#watch={link['websocket'].rsplit('/', 2)[1]}&token=" + link["viewer_token"]
    )
    assert out["welcome"]["role"] == "viewer"
    # It saw the map (the backlog first, then live chunks), the camera and the drone.
    viewer = out["viewer"]
    chunks = [m for m in viewer if m["type"] == "map_chunk"]
    assert chunks[0]["chunk"] == 0 and sum(c["count"] for c in chunks) > 1000
    assert sum(c["count"] for c in chunks) <= chunks[-1]["total_points"]
    states = [m for m in viewer if m["type"] == "drone_state"]
    assert len(states) > 20
    assert {m["seq"] for m in viewer if m["type"] == "pose"} >= {FRAMES - 1}
    assert out["viewer_landing"]["mode"] in ("landing", "landed")
    assert any(m["type"] == "drone_state" for m in out["second"])

    # Its commands and its frame were refused with read_only and changed nothing.
    for error in out["refused"]:
        assert error["name"] == "read_only" and not error["fatal"], error
    after = out["owner_states_after"]
    assert len(after) > 10
    assert all(s.get("command_id") not in (77, 78) for s in after)
    assert all(s["mode"] != "goto" and s["mode"] != "landing" for s in after)
    moved = np.linalg.norm(
        proto.pose_matrix(after[-1], "T_world_drone")[:3, 3]
        - proto.pose_matrix(after[0], "T_world_drone")[:3, 3]
    )
    assert moved < 0.05, f"the drone moved {moved:.3f} m"
    assert not out["owner_errors"], out["owner_errors"]
    assert out["owner_poses"] == FRAMES

    # On the owner's socket the viewer token is a stranger's.
    assert out["intruder_close"] == proto.CLOSE_CODES["unauthorized"]
    assert out["intruder_error"][0]["name"] == "unauthorized"

    assert len(out["listed"]) == 2 and link["viewer_id"] in out["listed"]
    assert out["revoke_status"] == 204
    assert out["revoked_close"] == proto.CLOSE_CODES["unauthorized"]
    assert "revoked" in out["revoked_error"]["message"]
    assert out["again_close"] == proto.CLOSE_CODES["unauthorized"]
    assert out["unknown_revoke"] == 404
    assert out["second_still_watching"]
    assert out["deleted_close"] == proto.CLOSE_CODES["unauthorized"]
