"""The drone through the real server: stream real frames, then pilot it over the WebSocket."""

from __future__ import annotations

import asyncio
import contextlib
import time

import numpy as np
import websockets

from server import protocol as proto
from server.datasets import open_dataset
from server.simulation.config import SimulationConfig
from tests.conftest import session_status

FRAMES = 40


class Pilot:
    """A minimal phone: streams frames in lock-step and keeps every message the server sends."""

    def __init__(self, ws) -> None:
        self.ws = ws
        self.messages: list[dict] = []
        self.arrived = asyncio.Event()

    async def receive(self) -> None:
        async for data in self.ws:
            self.messages.append(proto.decode(data, direction=proto.SERVER_TO_CLIENT))
            self.arrived.set()

    def of(self, kind: str, **match) -> list[dict]:
        return [
            m
            for m in self.messages
            if m["type"] == kind and all(m.get(k) == v for k, v in match.items())
        ]

    async def wait_for(self, kind: str, timeout: float = 20.0, **match) -> dict:
        deadline = time.monotonic() + timeout
        while not (found := self.of(kind, **match)):
            self.arrived.clear()
            remaining = deadline - time.monotonic()
            assert remaining > 0, (
                f"no {kind} {match} within {timeout} s; last: {self.messages[-3:]}"
            )
            try:
                await asyncio.wait_for(self.arrived.wait(), remaining)
            except asyncio.TimeoutError:
                pass
        return found[0]

    async def send(self, message: dict) -> None:
        await self.ws.send(proto.encode(message))


def near_pixel(depth: np.ndarray, want_m: float = 1.6) -> tuple[float, float]:
    """A pixel whose surface is about want_m away, so the point in front of it is mapped."""
    v, u = np.mgrid[40 : depth.shape[0] - 40 : 20, 40 : depth.shape[1] - 40 : 20]
    z = depth[v, u]
    best = np.argmin(np.where(z > 0, np.abs(z - want_m), np.inf))
    return float(u.flat[best]), float(v.flat[best])


def drone_position(state: dict) -> np.ndarray:
    return proto.pose_matrix(state, "T_world_drone")[:3, 3]


async def flight_map_caught_up(server, sid: str, token: str, timeout_s: float = 30.0) -> float:
    """Seconds until the drone's flight map holds every frame fused into the map (status
    drone.map_frames == map.frames_integrated), once no frame is in flight: the mapping thread
    finishes the fusions queued, then hands the drone the rest (on a quiet machine within the
    3 s update interval plus its 1 s idle poll; a fixed bound would only measure the load)."""
    start = time.monotonic()
    while True:
        status = await asyncio.to_thread(session_status, server.url, sid, token)
        fused, held = status["map"]["frames_integrated"], status["drone"]["map_frames"]
        if fused > 0 and held == fused:
            return time.monotonic() - start
        assert time.monotonic() - start < timeout_s, f"the drone's map holds {held} of {fused}"
        await asyncio.sleep(0.2)


@contextlib.asynccontextmanager
async def piloting(server, sid: str, token: str, dataset, client_name: str):
    """Our socket to session ``sid``, its hello welcomed, and a Pilot keeping every message the
    server sends; on leaving: bye, and the receiver ends with the server's close."""
    K = dataset.intrinsics
    url = f"{server.ws_url}/ws/sessions/{sid}?token={token}"
    async with websockets.connect(url, max_size=None) as ws:
        pilot = Pilot(ws)
        receiver = asyncio.create_task(pilot.receive())
        hello = proto.make_hello(client_name, (K.fx, K.fy, K.cx, K.cy), (K.width, K.height))
        await pilot.send(hello)
        await pilot.wait_for("welcome")
        yield pilot
        await pilot.send(proto.make_bye())
        await asyncio.wait_for(receiver, 10)


async def fly(server, dataset) -> dict:
    sid, token = server.create_session()
    async with piloting(server, sid, token, dataset, "pilot-test") as pilot:
        for i in range(FRAMES):
            frame = dataset[i]
            await pilot.send(proto.make_frame(i, frame.timestamp, frame.colour, frame.depth))
            await pilot.wait_for("pose", seq=i)
        out = {"spawned": await pilot.wait_for("drone_event", event="spawned")}
        await pilot.wait_for("drone_state")
        # The frames stopped: the drone's map catches up with everything fused (without that
        # catch-up the target below sat in space the drone had not been told was free).
        out["caught_up_s"] = await flight_map_caught_up(server, sid, token)

        # 1. goto a place the camera looked at from close by: observed free space.
        poses = {m["seq"]: proto.pose_matrix(m) for m in pilot.of("pose")}
        target = poses[FRAMES // 2][:3, 3] + 0.7 * poses[FRAMES // 2][:3, 2]
        await pilot.send(proto.make_command(1, "goto", target=target))
        out["arrived"] = await pilot.wait_for(
            "drone_event", timeout=30.0, event="arrived", command_id=1
        )
        await asyncio.sleep(0.2)
        out["after_goto"] = pilot.of("drone_state")[-1]
        out["goto_states"] = pilot.of("drone_state", command_id=1)
        out["target"] = target

        # 2. a target far outside the map.
        await pilot.send(proto.make_command(2, "goto", target=[40.0, 0.0, 0.0]))
        out["unreachable"] = await pilot.wait_for("error", command_id=2)

        # 3. a tapped pixel of the last frame.
        last = FRAMES - 1
        pixel = near_pixel(dataset[last].depth)
        await pilot.send(proto.make_command(3, "goto_pixel", pixel=pixel, seq=last))
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and not (
            pilot.of("error", command_id=3) or pilot.of("drone_state", command_id=3)
        ):
            await asyncio.sleep(0.05)
        out["pixel_states"] = pilot.of("drone_state", command_id=3)
        out["pixel_errors"] = pilot.of("error", command_id=3)
        out["pixel"], out["pixel_pose"] = pixel, poses[last]

        # 4. hold, then land.
        await pilot.send(proto.make_command(4, "land"))
        out["landed"] = await pilot.wait_for("drone_event", timeout=20.0, event="landed")
        out["collisions"] = pilot.of("drone_event", event="collision")
        out["states"] = pilot.of("drone_state")
    return out


def test_a_streamed_session_spawns_a_drone_that_flies_where_the_pilot_says(
    live_server, shared_data
):
    dataset = open_dataset(shared_data / "synthetic_room0")
    server = live_server()
    out = asyncio.run(fly(server, dataset))
    radius = SimulationConfig().radius_m

    # It spawned in front of the first camera and flew to the target.
    assert np.linalg.norm(np.array(out["spawned"]["position"])) < 2.0
    arrival = np.linalg.norm(drone_position(out["after_goto"]) - out["target"])
    assert arrival < 0.15, f"{arrival:.3f} m from the target"
    routes = [s for s in out["goto_states"] if "route" in s]
    assert routes and len(routes[0]["route"]) >= 6  # at least two route points, flat xyz
    assert not out["collisions"]
    assert min(s["clearance"] for s in out["states"]) >= radius

    # T_camera_drone is the drone seen from the latest camera.
    state = out["states"][-1]
    T_world_camera = out["pixel_pose"]
    np.testing.assert_allclose(
        proto.pose_matrix(state, "T_camera_drone"),
        np.linalg.inv(T_world_camera) @ proto.pose_matrix(state, "T_world_drone"),
        atol=1e-6,
    )

    error = out["unreachable"]
    assert error["name"] == "unreachable_target" and not error["fatal"]
    assert "nearest" not in error or np.linalg.norm(error["nearest"]) < 10

    # The tapped pixel became a goto to the point it shows, standoff_m back towards the camera
    # (or the nearest reachable point close to it; test_flight checks the exact point).
    assert not out["pixel_errors"], out["pixel_errors"]
    frame = dataset[FRAMES - 1]
    u, v = (int(round(c)) for c in out["pixel"])
    z = np.median(frame.depth[v - 3 : v + 4, u - 3 : u + 4])
    K = dataset.intrinsics
    ray = np.array([(out["pixel"][0] - K.cx) / K.fx, (out["pixel"][1] - K.cy) / K.fy, 1.0])
    surface = T_world_camera[:3, :3] @ (ray * z) + T_world_camera[:3, 3]
    expected = surface - SimulationConfig().standoff_m * (
        T_world_camera[:3, :3] @ ray
    ) / np.linalg.norm(ray)
    got = np.array(out["pixel_states"][0]["target"])
    assert np.linalg.norm(got - expected) < 0.6, (got, expected)

    assert out["landed"]["command_id"] == 4  # the land command brought it down


def test_the_bundled_demo_session_maps_the_room_and_tours_the_drone(live_server):
    """`serve --demo`: the server replays its own demo sequence and a tour pilot flies the drone."""

    server = live_server(demo=True, demo_fps=10.0)
    deadline = time.monotonic() + 120
    status = {}
    while time.monotonic() < deadline:
        demo = server.app.state.demo
        if demo is not None:
            status = session_status(server.url, demo["id"], demo["token"])
            drone = status.get("drone") or {}
            # The mapping thread may lag the tracker on a busy machine: wait for it too.
            if (
                drone.get("events", {}).get("arrived", 0) >= 2
                and status["frames_processed"] > 20
                and status["map"]["frames_integrated"] > 5
            ):
                break
        time.sleep(0.5)
    assert status.get("frames_processed", 0) > 20, status
    assert status["map"]["frames_integrated"] > 5
    assert status["drone"]["events"].get("arrived", 0) >= 2, status["drone"]
    assert status["drone"]["events"].get("collision", 0) == 0
