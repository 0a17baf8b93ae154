"""The commands around a running server: ``serve`` runs one, ``loadtest`` streams to one."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated

import typer

from server.cli.common import (
    ConfigFile,
    ConfigSets,
    console,
    effective_config,
    err_console,
    open_sequence,
    print_config,
)
from server.errors import DroneSimError


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
    config = effective_config(config_file, sets, {"server": given})
    settings = config.server
    if settings.allocator == "jemalloc":
        from server.memory import restart_on_jemalloc

        restart_on_jemalloc()  # before the heavy imports below; returns only when it cannot
    from server.transport.app import make_server
    from server.transport.phone_link import certificate_hosts, phone_link

    print_config(config, "configuration")
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
    print_phone_link(phone_link(settings.host, settings.port, settings.tls, settings.phone_hosts))
    logging.getLogger().setLevel(logging.INFO)
    make_server(config, log_level="info", ssl_certfile=ssl_certfile, ssl_keyfile=ssl_keyfile).run()


def print_phone_link(link) -> None:
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
    lockstep: Annotated[
        bool,
        typer.Option(
            help="every client plays the same frame at once (else each starts elsewhere in the "
            "sequence, as phones in a room are each at another point of their walk)"
        ),
    ] = False,
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
    ds = open_sequence(dataset, None, None, None, None, None)
    with console.status(f"encoding {min(frames or len(ds), len(ds))} frames of {ds.name} ..."):
        sequence = lt.EncodedSequence.from_dataset(ds, frames, depth_format)
    cfg = lt.LoadTestConfig(
        url=url,
        sessions=sessions,
        fps=fps,
        duration_s=duration,
        max_in_flight=max_in_flight,
        command_every_s=command_every,
        lockstep=lockstep,
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
