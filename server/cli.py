"""Command line: ``python -m server track|evaluate``."""

from __future__ import annotations

import logging
import sys
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.table import Table

from server.errors import DroneSimError

app = typer.Typer(add_completion=False, no_args_is_help=True, help=__doc__)
console = Console()
err_console = Console(stderr=True, soft_wrap=True)


def _open(dataset: str, fx, fy, cx, cy, depth_scale):
    """Open a sequence folder, or the bundled demo sequence for the name 'demo'."""
    from server.datasets import open_dataset

    if dataset == "demo":
        from server.datasets.demo import demo_sequence_path

        return open_dataset(demo_sequence_path(), "tum")
    kwargs = {}
    if fx is not None:
        if None in (fy, cx, cy):
            raise DroneSimError("--fx needs --fy, --cx and --cy too")
        kwargs["intrinsics"] = _intrinsics_for(Path(dataset), fx, fy, cx, cy)
    if depth_scale is not None:
        kwargs["depth_scale"] = depth_scale
    return open_dataset(dataset, **kwargs)


def _intrinsics_for(path: Path, fx: float, fy: float, cx: float, cy: float):
    """Intrinsics from the command line; the image size is read off the first image."""
    import cv2

    from server.geometry import Intrinsics

    images = sorted(p for p in path.rglob("*") if p.suffix.lower() in (".png", ".jpg", ".jpeg"))
    if not images:
        raise DroneSimError(f"no images under {path}")
    h, w = cv2.imread(str(images[0]), cv2.IMREAD_UNCHANGED).shape[:2]
    return Intrinsics(fx, fy, cx, cy, w, h)


@app.command()
def track(
    dataset: Annotated[
        str, typer.Argument(help="sequence folder (TUM or Redwood layout), or 'demo'")
    ],
    out: Annotated[Path, typer.Option(help="results folder")] = Path("results/track"),
    frames: Annotated[int | None, typer.Option(help="only the first N frames")] = None,
    dense: Annotated[bool, typer.Option(help="dense point-to-plane refinement")] = True,
    fx: float | None = None,
    fy: float | None = None,
    cx: float | None = None,
    cy: float | None = None,
    depth_scale: Annotated[float | None, typer.Option(help="depth units per metre")] = None,
) -> None:
    """Register a sequence; write trajectory (TUM), map (PLY), a top-view picture and metrics."""
    from server.config import RegistrationConfig
    from server.evaluation.metrics import format_table
    from server.pipeline import run_odometry, write_outputs

    ds = _open(dataset, fx, fy, cx, cy, depth_scale)
    config = RegistrationConfig().with_overrides(solver={"dense": dense})
    run = run_odometry(ds, config, max_frames=frames)
    paths = write_outputs(run, out, ds, config)
    s = run.summary
    stats = Table(title=f"{ds.name}: registration")
    for col in ("frames", "keyframes", "ok", "weak", "lost", "median ms", "p90 ms"):
        stats.add_column(col, justify="right")
    st = s["states"]
    stats.add_row(
        str(s["frames"]),
        str(s["keyframes"]),
        str(st.get("ok", 0)),
        str(st.get("weak", 0)),
        str(st.get("lost", 0)),
        f"{s['median_ms']:.1f}",
        f"{s['p90_ms']:.1f}",
    )
    console.print(stats)
    if run.metrics is not None:
        console.print(
            format_table({"estimate": run.metrics}, title=f"{ds.name}: error vs ground truth")
        )
    for name, path in paths.items():
        console.print(f"{name:>10}: {path}")


@app.command("evaluate")
def evaluate_cmd(
    groundtruth: Annotated[Path, typer.Argument(help="ground truth, TUM format")],
    estimate: Annotated[Path, typer.Argument(help="estimate, TUM format")],
    max_diff: Annotated[float, typer.Option(help="timestamp tolerance, seconds")] = 0.02,
) -> None:
    """Print ATE and RPE of an estimated trajectory against ground truth."""
    from server.evaluation.metrics import evaluate, format_table
    from server.evaluation.trajectory import read_tum

    metrics = evaluate(read_tum(groundtruth), read_tum(estimate), max_diff=max_diff)
    console.print(format_table({estimate.name: metrics}))


@app.command()
def serve(
    host: Annotated[
        str | None, typer.Option(help="address to listen on (0.0.0.0: the LAN)")
    ] = None,
    port: Annotated[int | None, typer.Option(help="TCP port")] = None,
    data_dir: Annotated[Path | None, typer.Option(help="where sessions are stored")] = None,
    tls: Annotated[bool | None, typer.Option("--tls/--no-tls", help="HTTPS, self-signed")] = None,
    demo: Annotated[
        bool | None, typer.Option("--demo/--no-demo", help="replay the demo sequence")
    ] = None,
    ray: Annotated[
        str | None,
        typer.Option(
            "--ray",
            metavar="ADDRESS",
            help="run sessions as Ray actors: auto, ray://host:10001, or local",
        ),
    ] = None,
) -> None:
    """Run the server (settings from DRONESIM_* environment variables, overridden by flags)."""
    from pydantic import ValidationError

    from server.settings import Settings

    flags = {"host": host, "port": port, "data_dir": data_dir, "tls": tls, "demo": demo, "ray": ray}
    try:
        settings = Settings(**{k: v for k, v in flags.items() if v is not None})
    except ValidationError as exc:
        problems = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in exc.errors())
        raise DroneSimError(f"invalid settings: {problems}") from exc
    if settings.allocator == "jemalloc":
        from server.memory import restart_on_jemalloc

        restart_on_jemalloc()  # before the heavy imports below; returns only when it cannot
    from server.transport.app import make_server

    settings.data_dir.mkdir(parents=True, exist_ok=True)
    ssl = {}
    if settings.tls:
        from server.transport.tls import ensure_certificate, local_addresses

        cert, key = ensure_certificate(settings.data_dir / "tls")
        ssl = {"ssl_certfile": str(cert), "ssl_keyfile": str(key)}
        console.print(
            f"HTTPS with a self-signed certificate ({cert}); from a phone on the same "
            f"network open https://<this machine>:{settings.port}/ (addresses: "
            f"{', '.join(local_addresses())}) and accept the certificate once."
        )
    logging.getLogger().setLevel(logging.INFO)
    make_server(settings, log_level="info", **ssl).run()


@app.command()
def loadtest(
    dataset: Annotated[str, typer.Argument(help="sequence folder (TUM or Redwood), or 'demo'")],
    url: Annotated[str, typer.Option(help="the server's base URL")] = "http://127.0.0.1:8000",
    sessions: Annotated[int, typer.Option(min=1, help="concurrent clients, a session each")] = 4,
    fps: Annotated[float, typer.Option(min=0.1, help="capture rate per client")] = 15.0,
    duration: Annotated[float, typer.Option(min=0.5, help="capture time, seconds")] = 30.0,
    frames: Annotated[int | None, typer.Option(min=1, help="only the first N frames")] = None,
    max_in_flight: Annotated[int, typer.Option(min=1, help="unanswered frames at most")] = 2,
    depth_format: Annotated[str, typer.Option(help="zlib (as browsers send) or png")] = "zlib",
    command_every: Annotated[float, typer.Option(min=0, help="drone command period, s")] = 2.0,
    json_path: Annotated[Path | None, typer.Option("--json", help="report (JSON)")] = None,
    plot: Annotated[Path | None, typer.Option(help="latency over time (PNG)")] = None,
    keep_sessions: Annotated[bool, typer.Option(help="do not delete the sessions")] = False,
    insecure: Annotated[bool, typer.Option(help="accept a self-signed certificate")] = False,
) -> None:
    """Stream a sequence from N concurrent clients at F fps; print latency, throughput, drops and
    errors per session. Exits with 2 when any session saw an error or a failed request."""
    import asyncio
    import json

    from rich.progress import Progress, TextColumn, TimeElapsedColumn

    from server.client import loadtest as lt

    if depth_format not in ("png", "zlib"):
        raise DroneSimError(f"--depth-format must be png or zlib, got {depth_format!r}")
    ds = _open(dataset, None, None, None, None, None)
    with console.status(f"encoding {min(frames or len(ds), len(ds))} frames of {ds.name} ..."):
        sequence = lt.EncodedSequence.from_dataset(ds, frames, depth_format)
    cfg = lt.LoadTestConfig(
        url=url,
        sessions=sessions,
        fps=fps,
        duration_s=duration,
        max_in_flight=max_in_flight,
        command_every_s=command_every,
        keep_sessions=keep_sessions,
        insecure=insecure,
    )
    with Progress(
        TextColumn("{task.description}"), TimeElapsedColumn(), console=console, transient=True
    ) as progress:
        task = progress.add_task("connecting ...")
        logged = [0.0]

        def show(results, elapsed: float) -> None:
            line = lt.live_line(results, elapsed)
            progress.update(task, description=f"{elapsed:5.1f}/{duration:g} s | {line}")
            if not console.is_terminal and elapsed - logged[0] >= 5:  # logs: a line every 5 s
                logged[0] = elapsed
                console.print(f"{elapsed:5.1f} s | {line}")

        report = asyncio.run(lt.run_loadtest(sequence, cfg, on_progress=show))
    console.print(lt.report_table(report))
    console.print(lt.report_footer(report))
    if json_path is not None:
        json_path.parent.mkdir(parents=True, exist_ok=True)
        json_path.write_text(json.dumps(report, indent=1))
        console.print(f"report: {json_path}")
    if plot is not None:
        plot.parent.mkdir(parents=True, exist_ok=True)
        lt.write_plot(report, plot)
        console.print(f"plot: {plot}")
    failures = [f"session {s['index']}: {f}" for s in report["sessions"] for f in s["failures"]]
    if failures:
        more = f"\n  ... {len(failures) - 20} more" if len(failures) > 20 else ""
        err_console.print(
            f"[red]{len(failures)} failures:[/red]\n  " + "\n  ".join(failures[:20]) + more
        )
        raise typer.Exit(2)


def main() -> None:
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    try:
        app()
    except DroneSimError as exc:
        err_console.print(f"[red]error:[/red] {exc}")
        sys.exit(1)


if __name__ == "__main__":
    main()
