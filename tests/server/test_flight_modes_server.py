"""Flight modes over the real server: the command ``flight_mode`` (before the drone spawns, and
mid-flight), sticks in angle mode tilting the drone as drone_state reports it (flight_mode and
attitude), and bad values refused with a clear error while the drone keeps its mode."""

from __future__ import annotations

import asyncio
import time

import msgpack
import numpy as np
import websockets

from server import protocol as proto
from server.datasets import open_dataset
from server.simulation.config import SimulationConfig
from server.simulation.pilot_modes import expo
from tests.server.test_drone_server import Pilot

FRAMES = 30
CONFIG = SimulationConfig()


async def connect(server, sid: str, token: str, dataset):
    K = dataset.intrinsics
    ws = await websockets.connect(f"{server.ws_url}/ws/sessions/{sid}?token={token}", max_size=None)
    pilot = Pilot(ws)
    receiver = asyncio.create_task(pilot.receive())
    await pilot.send(proto.make_hello("modes-test", (K.fx, K.fy, K.cx, K.cy), (K.width, K.height)))
    await pilot.wait_for("welcome")
    return ws, pilot, receiver


async def fly(server, dataset) -> dict:
    sid, token = server.create_session()
    out: dict = {}
    ws, pilot, receiver = await connect(server, sid, token, dataset)
    # Set before the drone exists: accepted, and the drone spawns in angle mode.
    await pilot.send(proto.make_command(1, "flight_mode", flight_mode="angle"))
    for i in range(FRAMES):
        frame = dataset[i]
        await pilot.send(proto.make_frame(i, frame.timestamp, frame.colour, frame.depth))
        await pilot.wait_for("pose", seq=i)
    await pilot.wait_for("drone_event", event="spawned", timeout=30.0)
    await pilot.wait_for("drone_state")
    out["refused_early"] = pilot.of("error", command_id=1)
    out["first_state"] = pilot.of("drone_state")[0]

    # A flight_mode command without its field: bad_command, non-fatal.
    await ws.send(msgpack.packb({"type": "command", "id": 2, "name": "flight_mode"}))
    out["missing"] = await pilot.wait_for("error", command_id=2)

    # Half pitch forward in angle mode for 0.6 s, sticks at 20 Hz: the drone tilts nose down.
    start = len(pilot.messages)
    t_end = time.monotonic() + 0.6
    while time.monotonic() < t_end:
        await pilot.send(proto.make_command(3, "sticks", sticks=[0.0, 0.0, 0.5, 0.0]))
        await asyncio.sleep(0.05)
    for _ in range(10):  # then centred, still streaming (angle mode wants fresh sticks)
        await pilot.send(proto.make_command(4, "sticks", sticks=[0.0, 0.0, 0.0, 0.0]))
        await asyncio.sleep(0.05)
    out["flown"] = [m for m in pilot.messages[start:] if m["type"] == "drone_state"]
    out["events"] = [m for m in pilot.messages[start:] if m["type"] == "drone_event"]

    # An unknown mode breaks the schema's enum: invalid_field, fatal (close 4000), and the drone
    # keeps its mode: a new connection sees angle still.
    await ws.send(
        msgpack.packb({"type": "command", "id": 5, "name": "flight_mode", "flight_mode": "3d"})
    )
    out["bad"] = await pilot.wait_for("error", command_id=5)
    try:
        await asyncio.wait_for(receiver, 10)
    except websockets.ConnectionClosedError:
        pass  # the fatal error's close
    out["close_code"] = ws.close_code
    ws, pilot, receiver = await connect(server, sid, token, dataset)
    out["after_bad"] = await pilot.wait_for("drone_state")
    await pilot.send(proto.make_command(6, "flight_mode", flight_mode="acro"))
    out["acro"] = await pilot.wait_for("drone_state", command_id=6)
    await pilot.send(proto.make_bye())
    await asyncio.wait_for(receiver, 10)
    return out


def test_angle_mode_over_the_server_tilts_the_drone_and_bad_modes_change_nothing(
    live_server, shared_data
):
    dataset = open_dataset(shared_data / "synthetic_room0")
    out = asyncio.run(fly(live_server(), dataset))

    assert not out["refused_early"], out["refused_early"]
    first = out["first_state"]
    assert first["flight_mode"] == "angle" and first["mode"] == "hover"
    assert np.abs(first["attitude"][:2]).max() < 1.0  # spawned level

    missing = out["missing"]
    assert missing["name"] == "bad_command" and not missing["fatal"]
    assert "flight_mode" in missing["message"]

    # The server's states show the tilt the stick asks for (half stick through the expo: 15.5
    # degrees), nose down, reached within a few states; manual flight in angle mode.
    flown = out["flown"]
    assert flown and all(s["flight_mode"] == "angle" for s in flown)
    pitch = np.array([s["attitude"][1] for s in flown])
    want = expo(0.5, CONFIG.stick_expo) * CONFIG.angle_max_deg
    collided = [e for e in out["events"] if e["event"] == "collision"]
    assert collided or pitch.max() > want - 3.0, (pitch, want)
    assert pitch.max() < want + 3.0
    assert any(s["mode"] == "manual" and s.get("command_id") in (3, 4) for s in flown)
    # The attitude is T_world_drone's rotation against gravity (the hello gave none: up is the
    # first camera's -y): the body's tilt from up is acos(cos roll cos pitch).
    for s in flown:
        body_up = proto.pose_matrix(s, "T_world_drone")[:3, 2]
        tilt = np.degrees(np.arccos(np.clip(body_up @ [0.0, -1.0, 0.0], -1, 1)))
        roll, pitch_deg = np.radians(s["attitude"][:2])
        expected = np.degrees(np.arccos(np.cos(roll) * np.cos(pitch_deg)))
        assert abs(tilt - expected) < 0.01, (tilt, expected)

    bad = out["bad"]
    assert bad["name"] == "invalid_field" and bad["fatal"] and "flight_mode" in bad["message"]
    assert out["close_code"] == 4000
    assert out["after_bad"]["flight_mode"] == "angle"  # nothing changed
    assert out["acro"]["flight_mode"] == "acro"
