"""Shared rooms: phones that join a live room, placed in it and fusing into its one map
(server/sessions/web/shared_rooms.py, server/sessions/processes/room_map.py).

Starts ``python -m server serve`` (a fresh data dir), then:

1. the owner's phone streams the first part of SEQUENCE at --fps (every --step-th frame of the
   recording, so the camera moves at its real speed), as a phone would (at most 2 frames in
   flight, newer frames dropped while busy), and its map catches up;
2. the owner invites, and --phones - 1 phones join (``POST /api/sessions`` ``{"join": id}``);
3. every phone streams at once, the owner its second part, each joined phone a part of its own
   (``--parts``: first:last of the recording, a reversed range walks back).

A run per ``--phones`` count (a fresh server each), summed up in one table.

Per phone: frames until placed (the first pose not ``lost``) and seconds from its first frame to
that pose, poses per second, latency p95, and the ATE of its placed poses against the
recording's ground truth (in the owner's world: the owner's first camera, frame 0, is the
origin), each phone aligned alone (SE(3)) and all phones with one alignment. Also the server's
CPU over step 3 (its whole process tree, as benchmarks/capacity.py measures it) per processed
frame and per phone, and the room's map (frames fused, blocks).

Target (issue 35): one alignment over all phones within 1.5x of the worst phone's own ATE.

    python benchmarks/shared_room.py [SEQUENCE] [--phones 2 3] [--fps 15]

Writes <out>/shared_room.md and shared_room.json.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import platform
import shlex
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # run from anywhere, installed or not

from capacity import TreeSampler, server_environment, wait_until_settled  # noqa: E402
from provenance import git_commit, utc_stamp  # noqa: E402

from server.client import rest  # noqa: E402
from server.client.replay import replay  # noqa: E402
from server.client.server_process import ServerProcess  # noqa: E402
from server.datasets import open_dataset  # noqa: E402
from server.datasets.there_and_back import Reordered  # noqa: E402
from server.evaluation.metrics import ate  # noqa: E402
from server.evaluation.trajectory import Trajectory  # noqa: E402
from server.geometry import invert  # noqa: E402
from server.pipeline import ground_truth_pose_at  # noqa: E402

TARGET_RATIO = 1.5  # one alignment over all phones, against the worst phone's own


def part(text: str, step: int, n: int) -> list[int]:
    """``first:last`` of the recording (clipped to its n frames), every ``step``-th frame;
    first > last walks back."""
    first, last = (int(v) for v in text.split(":"))
    first, last = min(first, n - 1), min(last, n - 1)
    return list(range(first, last, step if last >= first else -step))


def post(url: str, token: str, body: dict | None = None) -> dict:
    """A POST with a bearer token and an optional JSON body; the answer, or SystemExit."""
    import urllib.request

    data = None if body is None else json.dumps(body).encode()
    req = urllib.request.Request(url, data=data, method="POST")
    req.add_header("Authorization", f"Bearer {token}")
    if data is not None:
        req.add_header("Content-Type", "application/json")
    with urllib.request.urlopen(req, timeout=60) as response:
        return json.loads(response.read())


def wait_for_map(server: ServerProcess, sid: str, token: str, timeout_s: float = 120.0) -> dict:
    """The session's status once its mapping thread has caught up."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        _, status = rest.request("GET", rest.sessions_url(server.url, sid), token)
        if status and status.get("fusion_waiting") == 0:
            return status
        time.sleep(0.3)
    raise SystemExit(f"session {sid}: the map did not catch up in {timeout_s:.0f} s")


class Phone:
    """One phone's session and what it streamed: the recording's frame indices in the order
    sent, and (arrival time, pose) of every answer."""

    def __init__(self, name: str, sid: str, token: str, ws_url: str) -> None:
        self.name, self.sid, self.token = name, sid, token
        self.url = f"{ws_url}/ws/sessions/{sid}"
        self.frames: list[int] = []
        self.poses: list[tuple[float, dict]] = []
        self.stats = None

    async def stream(self, ds, frames: list[int], fps: float) -> None:
        self.frames = frames
        self.stats = await replay(
            self.url,
            self.token,
            Reordered(ds, frames, name=f"{ds.name}_{self.name}"),
            fps=fps,
            depth_format="zlib",
            client_name=self.name,
            on_pose=lambda p: self.poses.append((time.monotonic(), p)),
            preencode=True,
        )

    @property
    def first_sent(self) -> float:
        """When the first frame went out: its answer's arrival less its latency (``replay``
        encodes every frame before the stream starts)."""
        return self.poses[0][0] - self.stats.latencies_ms[0] / 1e3

    def placed(self) -> tuple[int | None, float | None]:
        """(frames sent before the first placed pose, seconds from the first frame sent to
        it), or (None, None)."""
        for t, p in self.poses:
            if p["state"] != "lost":
                return p["seq"], t - self.first_sent
        return None, None

    def trajectory(self, ds, T_room_truth: np.ndarray) -> tuple[Trajectory, Trajectory]:
        """(truth in the owner's world, estimate) of the placed poses."""
        kept = [p for _, p in self.poses if p["state"] != "lost"]
        idx = [self.frames[p["seq"]] for p in kept]
        stamps = np.array([ds.timestamps[i] for i in idx], dtype=np.float64)
        truth = np.array([T_room_truth @ ground_truth_pose_at(ds, t) for t in stamps])
        est = np.array([pose_matrix(p) for p in kept])
        return Trajectory(stamps, truth), Trajectory(stamps, est)


def pose_matrix(pose: dict) -> np.ndarray:
    from server import protocol

    return protocol.pose_matrix(pose)


def joined(trajectories: list[Trajectory]) -> Trajectory:
    return Trajectory(
        np.concatenate([t.timestamps for t in trajectories]),
        np.concatenate([t.poses for t in trajectories]),
    )


def run(args: argparse.Namespace, phone_count: int) -> dict:
    """One run with ``phone_count`` phones (the owner's included)."""
    ds = open_dataset(args.sequence)
    n = len(ds)
    T_room_truth = invert(ground_truth_pose_at(ds, ds.timestamps[0]))
    first = part(args.first, args.step, n)
    parts = [part(p, args.step, n) for p in args.parts[:phone_count]]
    if len(parts) < phone_count:
        raise SystemExit(f"--parts names {len(parts)} parts for {phone_count} phones")
    with (
        tempfile.TemporaryDirectory() as tmp,
        ServerProcess(Path(tmp) / "data", env=server_environment(phone_count + 2)) as server,
    ):
        wait_until_settled(server.pid)
        sid, token = server.create_session()
        owner = Phone("owner", sid, token, server.ws_url)
        print(f"owner maps frames {first[0]}-{first[-1]} ...", flush=True)
        asyncio.run(owner.stream(ds, first, args.fps))
        owner_map = wait_for_map(server, sid, token)["map"]
        owner_first = owner.trajectory(ds, T_room_truth)
        phones = [Phone("owner", sid, token, server.ws_url)]
        sessions = rest.sessions_url(server.url)
        for k in range(1, phone_count):
            invite = post(f"{sessions}/{sid}/invites", token)
            created = post(sessions, invite["join_token"], {"join": sid})
            phones.append(Phone(f"phone{k + 1}", created["id"], created["token"], server.ws_url))
        print(f"{phone_count} phones stream at once ...", flush=True)

        async def together() -> None:
            streams = zip(phones, parts, strict=True)
            await asyncio.gather(*(p.stream(ds, f, args.fps) for p, f in streams))

        with TreeSampler(server.pid) as sampler:
            asyncio.run(together())
        cpu = sampler.summary()
        room_map = wait_for_map(server, sid, token)["map"]

    rows, trajectories = [], []
    for phone in phones:
        truth, est = phone.trajectory(ds, T_room_truth)
        if phone.name == "owner":  # its first part too: it is the same session, one world
            truth, est = joined([owner_first[0], truth]), joined([owner_first[1], est])
        trajectories.append((truth, est))
        frames_to_place, seconds_to_place = phone.placed()
        stats = phone.stats
        lat = np.array(stats.latencies_ms) if stats.latencies_ms else np.array([np.nan])
        rows.append(
            {
                "phone": phone.name,
                "frames": f"{phone.frames[0]}-{phone.frames[-1]}",
                "sent": stats.sent,
                "poses": len(phone.poses),
                "poses_per_s": len(phone.poses) / max(1e-9, phone.poses[-1][0] - phone.first_sent)
                if phone.poses
                else 0.0,
                "p95_ms": float(np.percentile(lat, 95)),
                "frames_to_place": frames_to_place,
                "seconds_to_place": seconds_to_place,
                "placed": len(est),
                "ate_cm": 100 * ate(truth, est)["rmse"] if len(est) > 2 else None,
                "failure": stats.failure,
            }
        )
    own = [r["ate_cm"] for r in rows if r["ate_cm"] is not None]
    truth_all = joined([t for t, _ in trajectories])
    together = 100 * ate(truth_all, joined([e for _, e in trajectories]))["rmse"]
    processed = sum(len(p.poses) for p in phones)
    return {
        "rows": rows,
        "ate_together_cm": together,
        "ate_worst_own_cm": max(own) if own else None,
        "meets": bool(own) and together <= TARGET_RATIO * max(own),
        "cpu_cores": cpu["cores"],
        "cpu_ms_per_frame": 1e3 * cpu["cpu_s"] / max(1, processed) if cpu["cpu_s"] else None,
        "owner_map": owner_map,
        "room_map": room_map,
    }


def summary(results: dict[int, dict]) -> list[str]:
    """One row per run: what a room of that many phones gets."""
    lines = [
        "| phones | poses/s per phone (least) | p95 ms (most) | s to placed (most, joined) "
        "| ATE one alignment cm | worst alone cm | server cores | CPU ms / frame | meets |",
        "|--:|--:|--:|--:|--:|--:|--:|--:|---|",
    ]
    for phones, r in sorted(results.items()):
        joined = [x["seconds_to_place"] for x in r["rows"][1:]]
        placed = "-" if None in joined or not joined else f"{max(joined):.2f}"
        lines.append(
            f"| {phones} | {min(x['poses_per_s'] for x in r['rows']):.1f} | "
            f"{max(x['p95_ms'] for x in r['rows']):.0f} | {placed} | "
            f"{r['ate_together_cm']:.2f} | {r['ate_worst_own_cm']:.2f} | {r['cpu_cores']:.2f} | "
            f"{r['cpu_ms_per_frame']:.0f} | {'yes' if r['meets'] else 'no'} |"
        )
    return lines


def markdown(results: dict[int, dict], meta: dict) -> str:
    lines = [
        "# Shared room",
        "",
        f"{meta['date']}; commit {meta['commit']}; {meta['machine']}, {meta['cores']} cores; "
        f"load average {meta['load_before']:.2f} before.",
        "",
        f"Command: `{meta['command']}`",
        "",
        f"Sequence {meta['dataset']}: the owner maps frames {meta['first']} alone, then the "
        f"phones stream at once at {meta['fps']:g} fps (one recorded frame in {meta['step']}). "
        "A phone's first frames are answered `lost` until it is placed in the room; the owner "
        "is placed from its first frame. Target: one alignment over all phones within "
        f"{TARGET_RATIO}x of the worst phone's own ATE.",
        "",
        *summary(results),
        "",
    ]
    for phones, result in sorted(results.items()):
        lines += [f"## {phones} phones", "", *_run_table(result)]
    return "\n".join(lines)


def _run_table(result: dict) -> list[str]:
    lines = [
        "| phone | frames | sent | poses | poses/s | p95 ms | frames to placed | s to placed "
        "| placed poses | ATE alone cm | failure |",
        "|---|---|--:|--:|--:|--:|--:|--:|--:|--:|---|",
    ]
    for r in result["rows"]:
        s = r["seconds_to_place"]
        ate_cm = "-" if r["ate_cm"] is None else f"{r['ate_cm']:.2f}"
        lines.append(
            f"| {r['phone']} | {r['frames']} | {r['sent']} | {r['poses']} | "
            f"{r['poses_per_s']:.1f} | {r['p95_ms']:.0f} | {r['frames_to_place']} | "
            f"{'-' if s is None else f'{s:.2f}'} | {r['placed']} | {ate_cm} | "
            f"{r['failure'] or ''} |"
        )
    worst = result["ate_worst_own_cm"]
    lines += [
        "",
        f"**All phones, one SE(3) alignment: ATE {result['ate_together_cm']:.2f} cm**, the worst "
        f"phone alone {worst:.2f} cm; target <= {TARGET_RATIO}x: "
        f"**{'PASS' if result['meets'] else 'FAIL'}**.",
        "",
        f"Server CPU while all phones streamed: {result['cpu_cores']:.2f} cores, "
        f"{result['cpu_ms_per_frame']:.0f} ms per processed frame (whole process tree). The "
        f"room's map: {result['owner_map']['frames_integrated']} frames fused by the owner "
        f"alone, {result['room_map']['frames_integrated']} at the end "
        f"({result['room_map']['active_blocks']} blocks).",
        "",
    ]
    return lines


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "sequence", nargs="?", default=str(REPO.parent / "shared" / "data" / "tum_fr1_xyz")
    )
    parser.add_argument("--phones", type=int, nargs="+", default=[2, 3])
    parser.add_argument("--fps", type=float, default=15.0)
    parser.add_argument("--step", type=int, default=2, help="every n-th recorded frame")
    parser.add_argument("--first", default="0:200", help="the owner's part mapped alone")
    parser.add_argument(
        "--parts",
        nargs="+",
        default=["200:400", "400:600", "300:0"],
        help="each phone's part, owner first (first:last; reversed walks back)",
    )
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results")
    args = parser.parse_args()
    meta = {
        "date": utc_stamp(),
        "commit": git_commit(),
        "command": shlex.join(["python", *sys.argv]),
        "machine": platform.platform(),
        "cores": os.cpu_count(),
        "load_before": os.getloadavg()[0],
        "dataset": Path(args.sequence).name,
        "phones": args.phones,
        "fps": args.fps,
        "step": args.step,
        "first": args.first,
    }
    results = {phones: run(args, phones) for phones in args.phones}
    text = markdown(results, meta)
    print(text)
    args.out.mkdir(parents=True, exist_ok=True)
    runs = {str(k): v for k, v in results.items()}
    (args.out / "shared_room.json").write_text(json.dumps({"meta": meta, "runs": runs}, indent=1))
    (args.out / "shared_room.md").write_text(text)
    print(f"wrote {args.out / 'shared_room.md'} and shared_room.json")
    ok = all(r["meets"] and not any(x["failure"] for x in r["rows"]) for r in results.values())
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
