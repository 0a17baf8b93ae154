"""The load test's report: counts, rates and latency percentiles per session and in total."""

from __future__ import annotations

from collections import Counter

import numpy as np

from server.client.loadtest.results import LoadTestConfig, SessionResult
from server.client.loadtest.sequence import EncodedSequence


def _percentiles(values) -> dict:
    v = np.asarray(values, dtype=float)
    if not len(v):
        return {"p50_ms": None, "p95_ms": None, "p99_ms": None, "mean_ms": None, "max_ms": None}
    p50, p95, p99 = np.percentile(v, [50, 95, 99])
    return {
        "p50_ms": float(p50),
        "p95_ms": float(p95),
        "p99_ms": float(p99),
        "mean_ms": float(v.mean()),
        "max_ms": float(v.max()),
    }


def _rates(
    captured: int,
    sent: int,
    processed: int,
    client_dropped: int,
    server_dropped: int,
    duration_s: float,
) -> dict:
    return {
        "processed_fps": processed / duration_s,
        "client_drop_rate": client_dropped / captured if captured else 0.0,
        "server_drop_rate": server_dropped / sent if sent else 0.0,
        # Every captured frame without a pose: dropped on either side, refused or unanswered.
        "drop_rate": 1 - processed / captured if captured else 0.0,
    }


def _session_report(r: SessionResult, duration_s: float) -> dict:
    return {
        "index": r.index,
        "id": r.id,
        "captured": r.captured,
        "sent": r.sent,
        "processed": r.processed,
        "client_dropped": r.client_dropped,
        "server_dropped": r.server_dropped,
        "unanswered": r.unanswered,
        **_rates(r.captured, r.sent, r.processed, r.client_dropped, r.server_dropped, duration_s),
        "latency": _percentiles([ms for _, ms in r.latency]),
        "send_lag_p95_ms": float(np.percentile(r.send_lag_ms, 95)) if r.send_lag_ms else None,
        "states": dict(r.states),
        "recoveries": dict(r.recoveries),
        "errors": dict(r.errors),
        "failures": r.failures,
        "commands": {
            "sent": r.commands_sent,
            "not_ready": r.commands_not_ready,
            "drone_states": r.drone_states,
            "drone_events": dict(r.drone_events),
        },
        "map_points": r.map_points,
        "close_code": r.close_code,
        "server_status": r.server_status,
    }


def build_report(
    results: list[SessionResult],
    cfg: LoadTestConfig,
    seq: EncodedSequence,
    wall_s: float,
    client_cpu_percent: float,
) -> dict:
    """Per session and total: counts, rates, latency percentiles, server stage times, failures;
    plus each session's latency timeline [[t_s, ms], ...] for plots."""
    d = cfg.duration_s
    totals = {
        k: sum(getattr(r, k) for r in results)
        for k in ("captured", "sent", "processed", "client_dropped", "server_dropped", "unanswered")
    }
    stages: dict[str, list[float]] = {}
    for r in results:
        for stage, values in r.stages_ms.items():
            stages.setdefault(stage, []).extend(values)
    errors = sum((r.errors for r in results), Counter())
    return {
        "config": {
            **cfg.__dict__,
            "dataset": seq.name,
            "frames": len(seq.frames),
            "size": list(seq.size),
            "mean_frame_bytes": seq.mean_bytes,
        },
        "wall_s": wall_s,
        "client_cpu_percent": client_cpu_percent,
        "total": {
            **totals,
            **_rates(
                totals["captured"],
                totals["sent"],
                totals["processed"],
                totals["client_dropped"],
                totals["server_dropped"],
                d,
            ),
            "processed_fps_per_session": totals["processed"] / d / max(1, len(results)),
            "latency": _percentiles([ms for r in results for _, ms in r.latency]),
            "errors": dict(errors),
            "failures": sum(len(r.failures) for r in results),
        },
        "stages_ms": {
            k: {
                "median": float(np.median(v)),
                "p95": float(np.percentile(v, 95)),
                "mean": float(np.mean(v)),
            }
            for k, v in sorted(stages.items())
        },
        "sessions": [_session_report(r, d) for r in results],
        "timeline": [[[round(t, 4), round(ms, 3)] for t, ms in r.latency] for r in results],
    }


def live_line(results: list[SessionResult], elapsed_s: float) -> str:
    """One line of progress: poses/s, p95 so far, drops and errors over all sessions."""
    latencies = [ms for r in results for _, ms in r.latency]
    p95 = f"{np.percentile(latencies, 95):.0f} ms" if latencies else "-"
    captured = sum(r.captured for r in results) or 1
    return (
        f"{sum(r.id is not None for r in results)} sessions | "
        f"{sum(r.processed for r in results) / max(elapsed_s, 1e-3):.1f} poses/s | p95 {p95} | "
        f"client drops {100 * sum(r.client_dropped for r in results) / captured:.1f}% | "
        f"server drops {sum(r.server_dropped for r in results)} | "
        f"failures {sum(len(r.failures) for r in results)}"
    )
