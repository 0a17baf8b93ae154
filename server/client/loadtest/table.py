"""The load test's report on a console: a table per session and a few summary lines."""

from __future__ import annotations


def _ms(value: float | None) -> str:
    return "-" if value is None else f"{value:.0f}"


def report_table(report: dict):
    """A rich table: one row per session and a total row. Errors: those counted as failures."""
    from rich import box
    from rich.table import Table

    c, t = report["config"], report["total"]
    table = Table(
        title=f"{c['sessions']} sessions x {c['fps']:g} fps x {c['duration_s']:g} s, "
        f"{c['dataset']} {c['size'][0]}x{c['size'][1]}: latency ms, drops",
        box=box.SIMPLE_HEAD,
        pad_edge=False,
        padding=(0, 1),
        collapse_padding=True,
    )
    # Latency (ms) send to pose; drops: on the client, on the server; err: failures.
    for col in (
        "sess",
        "sent",
        "poses",
        "pose/s",
        "drop c",
        "drop s",
        "p50",
        "p95",
        "p99",
        "ok/wk/lost",
        "err",
    ):
        table.add_column(col, justify="right")

    def row(name: str, s: dict, states: str, errors: int, style=None) -> None:
        table.add_row(
            name,
            str(s["sent"]),
            str(s["processed"]),
            f"{s['processed_fps']:.1f}",
            f"{100 * s['client_drop_rate']:.1f}%",
            f"{100 * s['server_drop_rate']:.1f}%",
            _ms(s["latency"]["p50_ms"]),
            _ms(s["latency"]["p95_ms"]),
            _ms(s["latency"]["p99_ms"]),
            states,
            str(errors),
            style=style,
        )

    for s in report["sessions"]:
        st = s["states"]
        row(
            str(s["index"]),
            s,
            f"{st.get('ok', 0)}/{st.get('weak', 0)}/{st.get('lost', 0)}",
            len(s["failures"]),
        )
    row("all", t, "", t["failures"], style="bold")
    return table


def report_footer(report: dict) -> str:
    """Stage times, drop rate against capture, client CPU and command answers in a few lines."""
    stages = ", ".join(
        f"{k} {v['median']:.1f}"
        for k, v in report["stages_ms"].items()
        if not k.startswith("track_")
    )
    commands = [s["commands"] for s in report["sessions"]]
    lags = [s["send_lag_p95_ms"] for s in report["sessions"] if s["send_lag_p95_ms"] is not None]
    t = report["total"]
    return (
        f"server stages, median ms: {stages or '-'}\n"
        f"frames captured {t['captured']}, without a pose {100 * t['drop_rate']:.1f}%; "
        f"client CPU {report['client_cpu_percent']:.0f}% of one core, "
        f"capture-to-send lag p95 {max(lags, default=0):.1f} ms\n"
        f"drone commands sent {sum(c['sent'] for c in commands)}, answered 'not ready' "
        f"{sum(c['not_ready'] for c in commands)} (tolerated), drone_state messages "
        f"{sum(c['drone_states'] for c in commands)}; errors by name: "
        f"{', '.join(f'{k} {v}' for k, v in report['total']['errors'].items()) or 'none'}"
    )
