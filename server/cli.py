"""Command line of the AR drone simulator: track, evaluate, serve, loadtest, config."""

from __future__ import annotations

import logging
import sys
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from server import __version__
from server.errors import DroneSimError

app = typer.Typer(no_args_is_help=True, help=__doc__, rich_markup_mode="markdown")
console = Console()
err_console = Console(stderr=True, soft_wrap=True)


def _print_version(value: bool) -> None:
    if value:
        console.print(f"dronesim-ar {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: Annotated[
        bool,
        typer.Option(
            "--version", callback=_print_version, is_eager=True, help="print the version and exit"
        ),
    ] = False,
) -> None:
    # The group's help is the module's docstring (Typer(help=...)).
    pass


# Every command that runs the pipeline or the server takes the configuration the same way.
ConfigFile = Annotated[
    Path | None,
    typer.Option(
        "--config",
        metavar="FILE",
        help="configuration file (YAML or TOML; `python -m server config` prints one)",
    ),
]
ConfigSets = Annotated[
    list[str] | None,
    typer.Option(
        "--set",
        metavar="KEY=VALUE",
        help="override one key, e.g. registration.keyframes.max_rotation_deg=10 (repeatable)",
    ),
]


def _load_config(config_file: Path | None, sets: list[str] | None, flags: dict | None = None):
    """The effective configuration (defaults < file < DRONESIM_* environment < --set < flags);
    a bad value stops the command here with a ConfigError naming the key."""
    from server.config import load_config

    return load_config(config_file, sets or (), flags)


def _print_config(config, title: str) -> None:
    console.rule(title)
    console.print(config.to_yaml().rstrip(), markup=False, highlight=False)
    console.rule()


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
    first = cv2.imread(str(images[0]), cv2.IMREAD_UNCHANGED)
    if first is None:
        raise DroneSimError(f"cannot read the image {images[0]}")
    h, w = first.shape[:2]
    return Intrinsics(fx, fy, cx, cy, w, h)


@app.command()
def track(
    dataset: Annotated[
        str,
        typer.Argument(
            help="sequence: a TUM or Redwood folder, a Stray Scanner export folder, a Record3D "
            ".r3d file, or 'demo'"
        ),
    ],
    out: Annotated[
        Path,
        typer.Option(
            help="folder of the runs: each run writes a new folder OUT/DATASET_DATE_TIME and "
            "OUT/latest links to the newest"
        ),
    ] = Path("results/track"),
    frames: Annotated[int | None, typer.Option(help="only N frames (from --start)")] = None,
    start: Annotated[int, typer.Option(min=0, help="begin at this frame (0 = the first)")] = 0,
    dense: Annotated[
        bool | None,
        typer.Option(
            "--dense/--no-dense",
            help="dense point-to-plane refinement (registration.solver.dense; default: on)",
        ),
    ] = None,
    device_prior: Annotated[
        bool | None,
        typer.Option(
            "--device-prior/--no-device-prior",
            help="an iPhone recording's own odometry as the tracker's prior "
            "(registration.prior.enabled; default: on)",
        ),
    ] = None,
    room: Annotated[
        Path | None,
        typer.Option(
            help="continue in the room saved by an earlier run (its run folder or the room "
            "folder in it; an --out folder means its latest run): relocalise by place "
            "recognition, track in its frame, extend it",
        ),
    ] = None,
    save_room: Annotated[
        bool,
        typer.Option(
            "--save-room/--no-save-room",
            help="keep the keyframes and save RUN/room (ORB features per keyframe, a TSDF "
            "fused from them behind tracking)",
        ),
    ] = True,
    mesh: Annotated[
        bool,
        typer.Option(
            "--mesh/--no-mesh",
            help="also write the keyframes' TSDF surface upright: RUN/mesh.ply (z up) and "
            "RUN/mesh.glb (y up, as glTF defines); up from the phone's gravity, else the map's "
            "floors and table tops, else the first camera",
        ),
    ] = False,
    overlap: Annotated[
        bool,
        typer.Option(
            "--overlap/--no-overlap",
            help="read frames ahead of the tracker and map behind it on threads of their own "
            "(same results; --no-overlap runs the stages in turn)",
        ),
    ] = True,
    fx: Annotated[
        float | None,
        typer.Option(help="focal length x, px (with --fy --cx --cy: overrides the dataset's)"),
    ] = None,
    fy: Annotated[float | None, typer.Option(help="focal length y, px")] = None,
    cx: Annotated[float | None, typer.Option(help="principal point x, px")] = None,
    cy: Annotated[float | None, typer.Option(help="principal point y, px")] = None,
    depth_scale: Annotated[float | None, typer.Option(help="depth units per metre")] = None,
    config_file: ConfigFile = None,
    sets: ConfigSets = None,
) -> None:
    """Register a sequence; write trajectory (TUM), map (PLY), a top-view picture, metrics, the
    configuration used (config.yaml: `--config RUN/config.yaml` runs it again), the room
    (RUN/room: keyframes and TSDF map, for a later --room) and with --mesh an upright mesh.
    RUN is a new folder under --out for each run; OUT/latest links to the newest. A Stray
    Scanner or Record3D recording's own odometry is each frame's prior unless
    --no-device-prior."""
    from server.config import write_config
    from server.evaluation.metrics import format_table
    from server.pipeline import run_odometry, write_outputs
    from server.results import link_latest, new_run_folder, room_folder

    registration: dict = {}
    if dense is not None:
        registration["solver"] = {"dense": dense}
    if device_prior is not None:
        registration["prior"] = {"enabled": device_prior}
    flags = {"registration": registration} if registration else {}
    config = _load_config(config_file, sets, flags)
    ds = _open(dataset, fx, fy, cx, cy, depth_scale)
    saved_room = None
    if room is not None:
        from server.rooms import load_room

        saved_room = load_room(room_folder(room), config.registration)
    _print_config(config, "configuration")
    run = run_odometry(
        ds,
        config.registration,
        max_frames=frames,
        mapping=config.mapping,
        room=saved_room,
        start=start,
        keep_room=save_room or mesh,  # the mesh is fused from the keyframes
        overlap=overlap,
    )
    if saved_room is not None and not run.summary["relocalisation"]["relocalised"]:
        raise DroneSimError(
            f"no frame of {ds.name} was recognised in the room {room}: nothing tracked"
        )
    folder = new_run_folder(out, ds.name)
    paths = write_outputs(run, folder, ds, config.registration, mesh=mesh, save_room=save_room)
    paths["config"] = write_config(config, folder / "config.yaml")
    latest = link_latest(folder)
    s = run.summary
    stats = Table(title=f"{ds.name}: registration")
    for col in ("frames", "keyframes", "ok", "weak", "lost", "repeated", "median ms", "p90 ms"):
        stats.add_column(col, justify="right")
    st = s["states"]
    stats.add_row(
        str(s["frames"]),
        str(s["keyframes"]),
        str(st.get("ok", 0)),
        str(st.get("weak", 0)),
        str(st.get("lost", 0)),
        str(sum(s.get("repeated", {}).values())),
        f"{s['median_ms']:.1f}",
        f"{s['p90_ms']:.1f}",
    )
    console.print(stats)
    prior = s["device_prior"]
    if prior["frames"]:
        console.print(
            f"device prior: {prior['frames']} frames carried the recording's odometry, "
            f"{prior['guesses']} started from it"
        )
    elif ds.device_poses is not None:
        console.print("device prior: off (the recording's odometry was not used)")
    found = s.get("relocalisation")
    if found is not None:
        console.print(
            f"relocalised in the room at frame {found['sequence_frame']} "
            f"(keyframe {found['keyframe']}, {found['inliers']} inliers, {found['ms']:.0f} ms; "
            f"{found['total_ms']:.0f} ms in all)"
        )
    if run.metrics is not None:
        console.print(
            format_table({"estimate": run.metrics}, title=f"{ds.name}: error vs ground truth")
        )
    upright = s.get("upright")
    if upright is not None:
        said = {"gravity": "the phone's gravity", "surfaces": "the map's floors and table tops"}
        console.print(f"mesh: up from {said.get(upright['source'], 'the first camera (-y)')}")
    for name, path in paths.items():
        console.print(f"{name:>10}: {path}")
    if latest is not None:
        console.print(f"{'latest':>10}: {latest} -> {folder.name}")


@app.command("evaluate")
def evaluate_cmd(
    groundtruth: Annotated[Path, typer.Argument(help="ground truth, TUM format")],
    estimate: Annotated[Path, typer.Argument(help="estimate, TUM format")],
    max_diff: Annotated[float, typer.Option(help="timestamp tolerance, seconds")] = 0.02,
    align: Annotated[
        str,
        typer.Option(
            help="how the estimate is aligned to the ground truth before the ATE: se3 (rigid), "
            "sim3 (with scale) or none"
        ),
    ] = "se3",
    delta: Annotated[float, typer.Option(help="the second RPE's step, in --delta-unit")] = 1.0,
    delta_unit: Annotated[
        str, typer.Option(help="what --delta counts: seconds or frames")
    ] = "seconds",
    json_out: Annotated[
        Path | None,
        typer.Option("--json", metavar="FILE", help="also write the metrics as JSON (metres, deg)"),
    ] = None,
    plot: Annotated[
        Path | None,
        typer.Option(
            metavar="FILE", help="also write a top view (PNG) of both, the estimate aligned"
        ),
    ] = None,
) -> None:
    """Print ATE and RPE of an estimated trajectory against ground truth (RPE per frame and
    over --delta); optionally write them as JSON and the two trajectories as a picture."""
    import json

    from server.evaluation.metrics import (
        ALIGNMENTS,
        DeltaUnit,
        aligned,
        associate_trajectories,
        evaluate,
        format_table,
    )
    from server.evaluation.trajectory import read_tum

    if align not in ALIGNMENTS:
        raise DroneSimError(f"--align must be one of {', '.join(ALIGNMENTS)}, not {align!r}")
    if delta_unit not in [u.value for u in DeltaUnit]:
        raise DroneSimError(f"--delta-unit must be seconds or frames, not {delta_unit!r}")
    gt, est = read_tum(groundtruth), read_tum(estimate)
    metrics = evaluate(gt, est, max_diff=max_diff, align=align, delta=delta, delta_unit=delta_unit)
    console.print(format_table({estimate.name: metrics}))
    if json_out is not None:
        report = {
            "groundtruth": str(groundtruth),
            "estimate": str(estimate),
            "align": align,
            "rpe_delta": {"value": delta, "unit": delta_unit},
            **metrics,
        }
        json_out.write_text(json.dumps(report, indent=2) + "\n")
    if plot is not None:
        from server.evaluation.plots import plot_top_view

        gt_m, est_m = associate_trajectories(gt, est, max_diff)  # as evaluate() paired them
        curves = {
            "ground truth": gt_m.poses,
            f"{estimate.stem} ({align})": aligned(gt_m, est_m, align).poses,
        }
        plot_top_view(plot, curves, title=f"{estimate.name} against {groundtruth.name}")


@app.command()
def serve(
    host: Annotated[
        str | None, typer.Option(help="address to listen on (0.0.0.0: the LAN)")
    ] = None,
    port: Annotated[int | None, typer.Option(help="TCP port")] = None,
    data_dir: Annotated[Path | None, typer.Option(help="where sessions are stored")] = None,
    tls: Annotated[bool | None, typer.Option("--tls/--no-tls", help="HTTPS, self-signed")] = None,
    phone_hosts: Annotated[
        list[str] | None,
        typer.Option(
            "--phone-host",
            metavar="HOST",
            help="an address or name phones reach this server by, beyond the LAN addresses it "
            "finds (e.g. the host's, in a container): named in the certificate, first in the "
            "phone URL (repeatable)",
        ),
    ] = None,
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
    config_file: ConfigFile = None,
    sets: ConfigSets = None,
) -> None:
    """Run the server. Configuration: defaults < --config FILE < DRONESIM_* environment
    variables < --set KEY=VALUE < the options --host, --port, --data-dir, --tls, --phone-host,
    --demo and --ray (each the server.* key of its name). Prints the URL a phone on the same
    network opens, and its QR code."""
    flags = {
        "host": host,
        "port": port,
        "data_dir": data_dir,
        "tls": tls,
        "phone_hosts": phone_hosts or None,  # typer gives [] when the option is absent
        "demo": demo,
        "ray": ray,
    }
    given = {k: v for k, v in flags.items() if v is not None}
    config = _load_config(config_file, sets, {"server": given})
    settings = config.server
    if settings.allocator == "jemalloc":
        from server.memory import restart_on_jemalloc

        restart_on_jemalloc()  # before the heavy imports below; returns only when it cannot
    from server.transport.app import make_server
    from server.transport.phone_link import certificate_hosts, phone_link

    _print_config(config, "configuration")
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    ssl_certfile = ssl_keyfile = None  # plain HTTP
    if settings.tls:
        from server.transport.tls import ensure_certificate

        hosts = certificate_hosts(settings.host, settings.phone_hosts)
        certificate = ensure_certificate(settings.data_dir / "tls", hosts)
        ssl_certfile, ssl_keyfile = str(certificate.cert), str(certificate.key)
        made = "a new" if certificate.issued else "the kept"
        console.print(
            f"HTTPS with {made} self-signed certificate ({certificate.cert}) for "
            f"{', '.join(certificate.hosts)}",
            highlight=False,
        )
    _print_phone_link(phone_link(settings.host, settings.port, settings.tls, settings.phone_hosts))
    logging.getLogger().setLevel(logging.INFO)
    make_server(config, log_level="info", ssl_certfile=ssl_certfile, ssl_keyfile=ssl_keyfile).run()


def _print_phone_link(link) -> None:
    """The URLs a phone opens, what its user must know, and the first URL's QR code."""
    from server.transport.phone_link import qr_text

    console.rule("phone")
    for url in link.urls:
        console.print(f"open on a phone on the same network: {url}", highlight=False)
    for note in link.notes:
        console.print(f"note: {note}", highlight=False)
    if link.urls:
        code = qr_text(link.urls[0])
        try:
            code.encode(console.encoding)
        except (UnicodeEncodeError, LookupError):  # a log or terminal without block characters
            console.print("(no QR code: this output cannot show its block characters)")
        else:
            console.print(code, markup=False, highlight=False, end="")
    console.rule()


@app.command()
def loadtest(
    dataset: Annotated[
        str,
        typer.Argument(help="sequence: TUM, Redwood, Stray Scanner folder, .r3d file, or 'demo'"),
    ],
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


@app.command("config")
def config_cmd(config_file: ConfigFile = None, sets: ConfigSets = None) -> None:
    """Print the effective configuration as YAML (defaults < --config FILE < DRONESIM_*
    environment < --set), to edit and pass back with --config."""
    config = _load_config(config_file, sets)
    sys.stdout.write(config.to_yaml())


def main() -> None:
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    try:
        app()
    except DroneSimError as exc:
        err_console.print(f"[red]error:[/red] {escape(str(exc))}")
        sys.exit(1)


if __name__ == "__main__":
    main()
