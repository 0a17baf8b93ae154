"""The load test's picture: latency over time per session with the rolling p95, and poses/s."""

from __future__ import annotations

import numpy as np

from server.client.loadtest.table import _ms


def write_plot(report: dict, path) -> None:
    """Latency over time (every pose, per session, with the rolling p95) and poses per second."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    c = report["config"]
    fig, (ax, ax_rate) = plt.subplots(
        2, 1, figsize=(10, 6.5), sharex=True, gridspec_kw={"height_ratios": [3, 1]}
    )
    everything = []
    for i, timeline in enumerate(report["timeline"]):
        if timeline:
            t, ms = np.asarray(timeline).T
            ax.scatter(t, ms, s=4, alpha=0.6, label=f"session {i}")
            everything.append(np.asarray(timeline))
    if everything:
        t, ms = np.concatenate(everything).T
        bins = np.arange(0.0, max(c["duration_s"], t.max()) + 1.0, 1.0)
        which = np.digitize(t, bins)
        centres = [bins[b - 1] + 0.5 for b in np.unique(which)]
        p95 = [np.percentile(ms[which == b], 95) for b in np.unique(which)]
        ax.plot(centres, p95, "k-", lw=1.5, label="p95 per second, all sessions")
        ax_rate.bar(bins[:-1] + 0.5, np.histogram(t, bins)[0], width=0.9, color="tab:gray")
    ax.set_ylim(bottom=0)
    ax.set_ylabel("send to pose, ms")
    ax.set_title(
        f"{c['sessions']} sessions x {c['fps']:g} fps, {c['dataset']}: "
        f"p95 {_ms(report['total']['latency']['p95_ms'])} ms"
    )
    ax.grid(alpha=0.3)
    if len(everything) <= 10:
        ax.legend(loc="upper right", fontsize=7, markerscale=3)
    ax_rate.axhline(c["sessions"] * c["fps"], color="tab:red", lw=1, label="captured per second")
    ax_rate.set_ylabel("poses / s")
    ax_rate.set_xlabel("time since start, s")
    ax_rate.legend(loc="lower right", fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
