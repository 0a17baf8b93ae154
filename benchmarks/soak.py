"""Soak: phones streaming to one server for a long time; its memory must stay flat, nothing may
fail, and no session's data may be lost.

Starts ``python -m server serve`` in its own process (a fresh data folder, a short session TTL so
that finished sessions are closed and saved during the run), then runs ``--sessions`` clients
for ``--minutes``. Each client streams a session of ``--session-minutes`` at ``--fps`` (the
sequence played forward and backward, pre-encoded, frames dropped on the phone while two await
answers; ``server/client/replay.py``), downloads its map and trajectory, checks them against
its status, and starts the next session. The server's memory is read from /proc every few
seconds: the PSS summed over its whole process tree (each live session is two processes).
At the end the server is stopped with SIGTERM, started again on the same folder, and every
session's map and trajectory are downloaded once more and compared with what the client got.

Writes ``benchmarks/results/soak.md`` and ``soak.png`` (RSS over time).

    python benchmarks/soak.py [SEQUENCE] [--minutes 30] [--sessions 4] [--fps 15]

The defaults are the capacity target (4 phones at 15 fps, ``benchmarks/capacity.py``). The load
tester (``server/client/loadtest.py``) does not hand out its sessions' tokens, which the final
downloads need, so the clients here are replay clients.
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import datetime
import os
import platform
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # run from anywhere, installed or not

import httpx  # noqa: E402
import numpy as np  # noqa: E402
import open3d as o3d  # noqa: E402
from capacity import memory_mb, scan_tree  # noqa: E402  (this folder: the process-tree readers)

from server.client.loadtest import ping_pong_index  # noqa: E402
from server.client.replay import replay  # noqa: E402
from server.client.server_process import ServerProcess, environment  # noqa: E402
from server.datasets import open_dataset  # noqa: E402
from server.datasets.base import RGBDDataset, RGBDFrame  # noqa: E402

RESULTS = REPO / "benchmarks" / "results"
RSS_GROWTH_LIMIT_MB_PER_MIN = 5.0  # over the second half of the run


class PingPong(RGBDDataset):
    """The first ``frames`` of a sequence forward, then backward, as one period: looping it keeps
    the camera's motion continuous. Timestamps increase at ``fps`` within a period; a replay
    that loops it starts them again each period (sequence numbers still rise, and they are
    what orders the frames on the server)."""

    def __init__(self, dataset: RGBDDataset, frames: int, fps: float) -> None:
        self.base, self.n, self.dt = dataset, min(frames, len(dataset)), 1.0 / fps
        self.name, self.path, self.intrinsics = dataset.name, dataset.path, dataset.intrinsics
        self.depth_scale = dataset.depth_scale

    def __len__(self) -> int:
        return max(1, 2 * self.n - 2)

    def __getitem__(self, i: int) -> RGBDFrame:
        frame = self.base[ping_pong_index(i, self.n)]
        return dataclasses.replace(frame, index=i, timestamp=i * self.dt)


# ---- the server ---------------------------------------------------------------------------------


def tree_memory_mb(pid: int) -> float:
    """PSS of the server and every process under it (workers, mappers, the forkserver), MB."""
    return sum(memory_mb(p) for p in scan_tree(pid))


class RSSSampler(threading.Thread):
    def __init__(self, server: ServerProcess, every_s: float) -> None:
        super().__init__(daemon=True)
        self.server, self.every_s = server, every_s
        self.t0 = time.monotonic()
        self.samples: list[tuple[float, float, int]] = []  # (s since start, MB, live sessions)
        self._done = threading.Event()

    def run(self) -> None:
        while True:
            try:
                live = self.server.health()["live_sessions"]
                self.samples.append(
                    (time.monotonic() - self.t0, tree_memory_mb(self.server.pid), live)
                )
            except (OSError, ValueError):  # a slow or restarting server: skip the sample
                pass
            if self._done.wait(self.every_s):
                return

    def stop(self) -> None:
        self._done.set()
        self.join()


# ---- the clients --------------------------------------------------------------------------------


@dataclasses.dataclass
class SessionRecord:
    """One streamed session, as its client saw it at the end."""

    client: int
    id: str
    token: str
    started_s: float
    sent: int = 0
    poses: int = 0
    errors: list[dict] = dataclasses.field(default_factory=list)
    status: dict | None = None
    trajectory: bytes = b""
    map_points: int = 0
    problems: list[str] = dataclasses.field(default_factory=list)


def ply_points(data: bytes, folder: Path) -> int:
    path = folder / "check.ply"  # the clients share one thread: one file at a time
    path.write_bytes(data)
    return len(o3d.io.read_point_cloud(str(path)).points)


async def run_client(
    index: int,
    server: ServerProcess,
    dataset: PingPong,
    args,
    deadline: float,
    t0: float,
    tmp: Path,
    records: list[SessionRecord],
) -> None:
    async with httpx.AsyncClient(base_url=server.url, timeout=120) as http:
        while time.monotonic() + 20 < deadline:  # a session of at least 20 s
            r = await http.post("/api/sessions")
            if r.status_code != 201:
                records.append(
                    SessionRecord(
                        index,
                        "-",
                        "-",
                        time.monotonic() - t0,
                        problems=[f"create: HTTP {r.status_code} {r.text}"],
                    )
                )
                await asyncio.sleep(5)
                continue
            body = r.json()
            record = SessionRecord(index, body["id"], body["token"], time.monotonic() - t0)
            records.append(record)
            seconds = min(args.session_minutes * 60, deadline - time.monotonic())
            try:
                stats = await replay(
                    f"{server.ws_url}/ws/sessions/{record.id}",
                    record.token,
                    dataset,
                    fps=args.fps,
                    max_frames=int(seconds * args.fps),
                    loop_sequence=True,
                    preencode=True,
                    client_name=f"soak/{index}",
                )
            except Exception as exc:  # any failure of a session is a finding, not a crash
                record.problems.append(f"stream: {type(exc).__name__}: {exc}")
                continue
            record.sent, record.poses, record.errors = stats.sent, len(stats.poses), stats.errors
            await asyncio.sleep(2.0)  # let the mapping thread fuse what it has queued
            headers = {"Authorization": f"Bearer {record.token}"}
            record.status = (await http.get(f"/api/sessions/{record.id}", headers=headers)).json()
            traj = await http.get(f"/api/sessions/{record.id}/trajectory.tum", headers=headers)
            ply = await http.get(f"/api/sessions/{record.id}/map.ply", headers=headers)
            record.trajectory = traj.content
            record.map_points = ply_points(ply.content, tmp) if ply.status_code == 200 else 0
            check_live(record)


def trajectory_poses(data: bytes) -> int:
    return sum(1 for line in data.decode().splitlines() if line and not line.startswith("#"))


def check_live(r: SessionRecord) -> None:
    if r.errors:
        r.problems.append(f"{len(r.errors)} error messages: {r.errors[:3]}")
    processed = (r.status or {}).get("frames_processed")
    if trajectory_poses(r.trajectory) != processed:
        r.problems.append(
            f"trajectory has {trajectory_poses(r.trajectory)} poses, status says "
            f"{processed} processed"
        )
    if processed is None or processed < r.poses:
        r.problems.append(f"client got {r.poses} poses, server processed {processed}")
    if r.map_points < 1000:
        r.problems.append(f"map has {r.map_points} points")


def check_after_restart(url: str, records: list[SessionRecord], tmp: Path) -> None:
    """Every session downloads from the restarted server: the same trajectory, the map whole."""
    for r in records:
        if r.status is None:
            continue
        headers = {"Authorization": f"Bearer {r.token}"}
        status = httpx.get(f"{url}/api/sessions/{r.id}", headers=headers, timeout=60)
        traj = httpx.get(f"{url}/api/sessions/{r.id}/trajectory.tum", headers=headers, timeout=60)
        ply = httpx.get(f"{url}/api/sessions/{r.id}/map.ply", headers=headers, timeout=120)
        if status.status_code != 200 or not status.json().get("closed"):
            r.problems.append(f"after restart: status HTTP {status.status_code}")
        if traj.content != r.trajectory:
            r.problems.append(
                f"after restart: trajectory differs ({trajectory_poses(traj.content)}"
                f" poses, {trajectory_poses(r.trajectory)} before)"
            )
        points = ply_points(ply.content, tmp) if ply.status_code == 200 else 0
        if points < 0.9 * r.map_points:
            r.problems.append(f"after restart: map has {points} points, {r.map_points} before")


# ---- report -------------------------------------------------------------------------------------


def rss_analysis(samples: list[tuple[float, float, int]], base_live: int) -> dict:
    """RSS rises while finished sessions wait for their TTL and falls when they close; what must
    stay flat is the level it falls back to. That base level is read while ``base_live``
    sessions are live (the clients streaming, none waiting), and its slope over the second half
    of the run is the figure."""
    t = np.array([s[0] for s in samples]) / 60.0
    rss = np.array([s[1] for s in samples])
    live = np.array([s[2] for s in samples])
    half = t >= t[-1] / 2
    base = (live == base_live) & half
    slope = float(np.polyfit(t[base], rss[base], 1)[0]) if base.sum() >= 3 else float("nan")
    first = (live == base_live) & ~half
    return {
        "start_mb": float(rss[0]),
        "end_mb": float(rss[-1]),
        "max_mb": float(rss.max()),
        "base_live_sessions": base_live,
        "base_first_half_mb": float(np.median(rss[first])) if first.any() else float("nan"),
        "base_second_half_mb": float(np.median(rss[base])) if base.any() else float("nan"),
        "base_slope_mb_per_min": slope,
        "samples": len(samples),
    }


def write_plot(samples, records: list[SessionRecord], args, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.array([s[0] for s in samples]) / 60.0
    fig, ax = plt.subplots(figsize=(9, 4))
    ax.plot(t, [s[1] for s in samples], color="tab:blue", label="server memory (tree PSS)")
    ax.set_xlabel("minutes")
    ax.set_ylabel("memory (MB)", color="tab:blue")
    ax.set_ylim(bottom=0)
    twin = ax.twinx()
    twin.step(
        t, [s[2] for s in samples], where="post", color="tab:grey", alpha=0.6, label="live sessions"
    )
    twin.set_ylabel("live sessions", color="tab:grey")
    twin.set_ylim(0, max(s[2] for s in samples) + 1)
    for r in records:
        ax.axvline(r.started_s / 60.0, color="tab:green", alpha=0.25, lw=0.8)
    ax.set_title(
        f"Soak: {args.sessions} x {args.fps:g} fps, sessions of "
        f"{args.session_minutes:g} min (green: a session starts)"
    )
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def write_report(
    path: Path,
    args,
    command: str,
    rss: dict,
    records,
    wall_min: float,
    load: tuple[float, float],
    log_problems: list[str],
    restart_ok: bool,
) -> bool:
    streamed = [r for r in records if r.status is not None]
    problems = [(r.id, p) for r in records for p in r.problems] + [
        ("server", p) for p in log_problems
    ]
    flat = not rss["base_slope_mb_per_min"] > RSS_GROWTH_LIMIT_MB_PER_MIN
    ok = flat and not problems and restart_ok and bool(streamed)
    short = args.minutes < 30
    lines = [
        f"# Soak{' — SHORT RUN' if short else ''}: {wall_min:.1f} min, {args.sessions} sessions "
        f"x {args.fps:g} fps",
        "",
    ]
    if short:
        lines += [
            f"> **Short run** ({args.minutes:g} min instead of 30) on a shared, loaded "
            "machine: it shows the soak works and what to look at; run "
            "`python benchmarks/soak.py` (30 min) on a quiet machine for the real figure.",
            "",
        ]
    lines += [
        f"{datetime.datetime.now():%Y-%m-%d %H:%M}; {platform.platform()}, {os.cpu_count()} cores,"
        f" load average {load[0]:.2f} before / {load[1]:.2f} after; sequence {args.sequence.name}"
        f" ({args.frames} frames, forward and backward); server settings: session TTL "
        f"{args.ttl_s:g} s, snapshots every 10 s"
        f"{', environment ' + ' '.join(args.server_env) if args.server_env else ''}.",
        "",
        f"Command: `{command}`",
        "",
        f"**Result: {'PASS' if ok else 'FAIL'}** — memory {'flat' if flat else 'GROWING'} "
        f"({rss['base_slope_mb_per_min']:+.1f} MB/min at its base level over the second half, "
        f"limit "
        f"{RSS_GROWTH_LIMIT_MB_PER_MIN:g}), {len(problems)} problems, "
        f"{len(streamed)} sessions streamed and all "
        f"{'found whole' if restart_ok and not problems else 'checked'} after a restart.",
        "",
        "| | |",
        "|---|--:|",
        f"| sessions streamed | {len(streamed)} |",
        f"| frames sent / poses received | {sum(r.sent for r in streamed)} / "
        f"{sum(r.poses for r in streamed)} |",
        f"| error messages from the server | {sum(len(r.errors) for r in records)} |",
        f"| server RSS at start / end / max (MB) | {rss['start_mb']:.0f} / {rss['end_mb']:.0f} / "
        f"{rss['max_mb']:.0f} |",
        f"| base level: RSS with {rss['base_live_sessions']} live sessions, median of the first / "
        f"second half (MB) | {rss['base_first_half_mb']:.0f} / {rss['base_second_half_mb']:.0f} |",
        f"| base level's slope over the second half (MB/min) | "
        f"{rss['base_slope_mb_per_min']:+.1f} |",
        "",
        "![RSS over time](soak.png)",
        "",
        "| client | session | started (min) | sent | poses | processed | trajectory | map points "
        "| problems |",
        "|--:|---|--:|--:|--:|--:|--:|--:|---|",
    ]
    for r in records:
        processed = (r.status or {}).get("frames_processed", "-")
        lines.append(
            f"| {r.client} | {r.id} | {r.started_s / 60:.1f} | {r.sent} | {r.poses} | "
            f"{processed} | {trajectory_poses(r.trajectory)} | {r.map_points} | "
            f"{'; '.join(r.problems) or '-'} |"
        )
    if log_problems:
        lines += ["", "Server log:", *[f"- {p}" for p in log_problems]]
    lines += [
        "",
        "How to read it: each client streams one session after another; a finished "
        "session stays live until the TTL closes and saves it, so RSS rises with the "
        "live sessions and falls as they close. Flat means the level it returns to (the "
        "base level, with only the streaming sessions live) does not creep up. After the "
        "run the server is stopped (SIGTERM) and started again, "
        "and every session's trajectory must download byte for byte as before and its map "
        "with at least 90 % of its points (fusion may still have added frames after the "
        "first download).",
    ]
    path.write_text("\n".join(lines) + "\n")
    return ok


# ---- main ---------------------------------------------------------------------------------------


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "sequence",
        nargs="?",
        type=Path,
        default=REPO.parent / "shared" / "data" / "synthetic_room0",
    )
    parser.add_argument("--minutes", type=float, default=30.0)
    parser.add_argument("--sessions", type=int, default=4)
    parser.add_argument("--fps", type=float, default=15.0)
    parser.add_argument("--session-minutes", type=float, default=5.0)
    parser.add_argument("--frames", type=int, default=60, help="frames of the sequence played")
    parser.add_argument("--ttl-s", type=float, default=60.0, help="server session TTL")
    parser.add_argument("--sample-s", type=float, default=5.0, help="RSS sampling period")
    parser.add_argument(
        "--server-env",
        nargs="*",
        default=[],
        metavar="NAME=VALUE",
        help="extra environment for the server, e.g. DRONESIM_ALLOCATOR=system",
    )
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    command = "python benchmarks/soak.py " + " ".join(sys.argv[1:])

    dataset = PingPong(open_dataset(args.sequence), args.frames, args.fps)
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="soak-") as tmp_name:
        tmp = Path(tmp_name)
        data_dir, log = tmp / "data", tmp / "server.log"
        env = {
            "DRONESIM_MAX_SESSIONS": str(2 * args.sessions + 2),
            "DRONESIM_CREATE_RATE_PER_MIN": "0",
            "DRONESIM_SESSION_TTL_S": str(args.ttl_s),
            **environment(args.server_env),
        }
        records: list[SessionRecord] = []
        with ServerProcess(data_dir, env, log) as server:  # killed if anything below fails
            sampler = RSSSampler(server, args.sample_s)
            sampler.start()
            t0 = time.monotonic()
            deadline = t0 + args.minutes * 60

            async def clients():
                await asyncio.gather(
                    *(
                        run_client(i, server, dataset, args, deadline, t0, tmp, records)
                        for i in range(args.sessions)
                    )
                )

            asyncio.run(clients())
            while time.monotonic() < deadline:  # a client's last session may end early
                time.sleep(1)
            sampler.stop()
            wall_min = (time.monotonic() - t0) / 60
            code = server.terminate()
        with ServerProcess(data_dir, env, log) as restarted:
            check_after_restart(restarted.url, records, tmp)
            restart_code = restarted.terminate()
        restart_ok = restart_code in (0, -signal.SIGTERM) and code in (0, -signal.SIGTERM)
        text = log.read_text()
        log_problems = [
            line
            for line in text.splitlines()
            if "Traceback" in line or line.startswith(("ERROR", "CRITICAL"))
        ]
    args.out.mkdir(parents=True, exist_ok=True)
    rss = rss_analysis(sampler.samples, base_live=args.sessions)
    write_plot(sampler.samples, records, args, args.out / "soak.png")
    ok = write_report(
        args.out / "soak.md",
        args,
        command,
        rss,
        records,
        wall_min,
        (load_before, os.getloadavg()[0]),
        log_problems,
        restart_ok,
    )
    print((args.out / "soak.md").read_text())
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
