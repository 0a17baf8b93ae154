"""Streaming rate of the phone page on a weak GPU: frames streamed per second while the page
replays the demo into a server that also runs its own demo session (the README's
``serve --demo``), in headless chromium at phone size (390x844, device pixel ratio 2) with
software WebGL (SwiftShader, on the same CPUs as the server).

Over ``--seconds`` (30) after the first ``--warmup`` (10) poses: frames sent and poses received
per second, the median send-to-pose latency and the server's part of it (``server_total``), the
share of the time the replay was held back waiting for a pose, and the page's own cost per
streamed frame: the renderer main thread's busy time (CDP ``Performance.getMetrics``
TaskDuration), of it the three.js draws' JavaScript, and the CPU of chromium's processes and of
the server's (cores). Target: >= 12 frames/s streamed (the page asks for 15).

``--base PATH`` measures a second checkout (e.g. a clone of the last commit, with its
``client_web/node_modules``) the same way in the same run, alternating the two ``--rounds``
times, so that the comparison shares the machine's load. Appends the table to
``benchmarks/results/page_stream.md``.

    python benchmarks/page_stream.py [--seconds S] [--base /tmp/page_base] [--rounds N]
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
import urllib.request
from contextlib import contextmanager
from pathlib import Path

from rich.console import Console
from rich.table import Table

sys.path.insert(0, str(Path(__file__).resolve().parent))
from page_fps import CHROMIUM, CHROMIUM_ARGS  # noqa: E402  (the same browser, as the tests')
from provenance import run_heading, utc_stamp  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results" / "page_stream.md"
TARGET_FPS = 12.0
CLOCK_HZ = os.sysconf("SC_CLK_TCK")

# Wrap the views' three.js draws (their JavaScript time) and note each pose's server time;
# works on any version of the page that has window.dronesim.{ar,map,fpv}.renderer.
INSTRUMENT_JS = """() => {
  const app = window.dronesim;
  const probe = { renderMs: 0, renders: 0, serverMs: [] };
  for (const view of [app.ar, app.map, app.fpv]) {
    const renderer = view.renderer;
    const original = renderer.render.bind(renderer);
    renderer.render = (...args) => {
      const t0 = performance.now();
      original(...args);
      probe.renderMs += performance.now() - t0;
      probe.renders += 1;
    };
  }
  app.client.addEventListener("pose", (e) => probe.serverMs.push(e.detail.timings_ms.server_total));
  // The page's own split of its main-thread work (page_load.js), where it has one.
  probe.kinds = {};
  const add = app.load?.add.bind(app.load);
  if (add) {
    app.load.add = (kind, ms, at) => {
      probe.kinds[kind] = (probe.kinds[kind] ?? 0) + ms;
      add(kind, ms, at);
    };
  }
  window.__probe = probe;
}"""

READ_JS = """() => {
  const app = window.dronesim, p = window.__probe, s = app.streamer;
  const chip = document.querySelector('[data-field=held]');
  return { sent: app.client.counts.sent, poses: app.client.counts.poses,
    latencyMs: app.client.latencyMs, skipped: s.skipped,
    heldMs: s.heldBackMs + (s.heldBack ? performance.now() - s.heldSince : 0),
    renderMs: p.renderMs, renders: p.renders, serverMs: p.serverMs.splice(0), kinds: { ...p.kinds },
    pixelRatio: app.ar.renderer.getPixelRatio(), budget: app.budget?.summary() ?? null,
    hud: chip && !chip.hidden ? chip.textContent : '' };
}"""


def tree_cpu_s(root_pid: int, name: str = "") -> float:
    """User + system CPU seconds of a process and its descendants (from /proc); with `name`,
    only those whose command name contains it."""
    children: dict[int, list[int]] = {}
    times: dict[int, float] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            comm, rest = stat.read_text().rsplit(")", 1)
        except OSError:
            continue
        fields, pid = rest.split(), int(stat.parent.name)
        children.setdefault(int(fields[1]), []).append(pid)
        if name in comm.split("(", 1)[1]:
            times[pid] = (int(fields[11]) + int(fields[12])) / CLOCK_HZ
    total, stack = 0.0, [root_pid]
    while stack:
        pid = stack.pop()
        total += times.get(pid, 0.0)
        stack.extend(children.get(pid, []))
    return total


def chromium_cpu_by_type(root_pid: int) -> dict[str, float]:
    """CPU seconds of the chromium processes under ``root_pid`` by their ``--type=`` (renderer,
    gpu-process, utility, ...; the browser process itself as "browser")."""
    out: dict[str, float] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            comm, rest = stat.read_text().rsplit(")", 1)
            cmdline = (stat.parent / "cmdline").read_bytes().replace(b"\0", b" ")
        except OSError:
            continue
        if "chrom" not in comm.split("(", 1)[1]:
            continue
        fields = rest.split()
        # Chromium rewrites its children's command lines (one string, not one argument each).
        found = re.search(rb"--type=([\w-]+)", cmdline)
        kind = found.group(1).decode() if found else "browser"
        out[kind] = out.get(kind, 0.0) + (int(fields[11]) + int(fields[12])) / CLOCK_HZ
    return out


@contextmanager
def demo_server(tree: Path, data_dir: Path, demo: bool):
    """``python -m server serve --demo`` from a checkout (its own server and page)."""
    from server.client.server_process import free_port

    port = free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "server", "serve", "--port", str(port), "--data-dir", str(data_dir)]
        + (["--demo"] if demo else ["--no-demo"]),
        cwd=tree,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 240  # slow to start on a loaded machine
        while True:
            try:
                with urllib.request.urlopen(f"{url}/healthz", timeout=1):
                    break
            except OSError:
                if proc.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError(f"the server in {tree} did not start") from None
                time.sleep(0.2)
        yield url, proc.pid
    finally:
        proc.kill()
        proc.wait(30)


def measure(browser, tree: Path, args) -> dict:
    """One run: a server from `tree` (with its demo session), the page streaming the demo."""
    with (
        tempfile.TemporaryDirectory() as tmp,
        demo_server(tree, Path(tmp), args.demo) as (url, pid),
    ):
        context = browser.new_context(
            viewport={"width": args.width, "height": args.height},
            is_mobile=True,
            has_touch=True,
            device_scale_factor=args.pixel_ratio,
        )
        page = context.new_page()
        cdp = context.new_cdp_session(page)
        cdp.send("Performance.enable")
        page.goto(f"{url}/?mode={args.mode}")
        page.wait_for_function("window.dronesim && window.dronesim.pilot", timeout=30_000)
        page.evaluate(INSTRUMENT_JS)
        page.tap("#btn-stream")
        page.wait_for_function(
            f"window.dronesim.client.counts.poses >= {args.warmup}", timeout=180_000, polling=200
        )

        def sample() -> dict:
            metrics = {m["name"]: m["value"] for m in cdp.send("Performance.getMetrics")["metrics"]}
            return {
                **page.evaluate(READ_JS),
                "task_s": metrics["TaskDuration"],
                "script_s": metrics["ScriptDuration"],
                "browser_cpu": tree_cpu_s(os.getpid(), "chrom"),
                "browser_by_type": chromium_cpu_by_type(os.getpid()),
                "server_cpu": tree_cpu_s(pid),
                "wall": time.monotonic(),
            }

        a = sample()
        page.wait_for_timeout(args.seconds * 1000)
        b = sample()
        context.close()
    span = b["wall"] - a["wall"]
    sent = b["sent"] - a["sent"]
    per_frame = 1000 / max(sent, 1)
    return {
        "sent_fps": sent / span,
        "pose_fps": (b["poses"] - a["poses"]) / span,
        "latency_ms": b["latencyMs"],
        "server_ms": statistics.median(b["serverMs"]) if b["serverMs"] else float("nan"),
        "held": (b["heldMs"] - a["heldMs"]) / 1000 / span,
        "page_ms": (b["task_s"] - a["task_s"]) * per_frame,
        "script_ms": (b["script_s"] - a["script_s"]) * per_frame,
        "render_ms": (b["renderMs"] - a["renderMs"]) / max(sent, 1),
        "kinds_ms": {k: (v - a["kinds"].get(k, 0)) / max(sent, 1) for k, v in b["kinds"].items()},
        "renders_per_s": (b["renders"] - a["renders"]) / span,
        "browser_cores": (b["browser_cpu"] - a["browser_cpu"]) / span,
        "browser_cores_by_type": {
            k: round((v - a["browser_by_type"].get(k, 0.0)) / span, 2)
            for k, v in b["browser_by_type"].items()
        },
        "server_cores": (b["server_cpu"] - a["server_cpu"]) / span,
        "pixel_ratio": b["pixelRatio"],
        "hud": b["hud"],
        "budget": b["budget"],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--warmup", type=int, default=10, help="poses before measuring")
    parser.add_argument("--width", type=int, default=390)
    parser.add_argument("--height", type=int, default=844)
    parser.add_argument("--pixel-ratio", type=float, default=2.0)
    parser.add_argument("--mode", default="demo", help="the page's capture mode (demo, demo-small)")
    parser.add_argument(
        "--no-demo", dest="demo", action="store_false", help="no server demo session"
    )
    parser.add_argument("--base", type=Path, help="another checkout to measure the same way")
    parser.add_argument("--rounds", type=int, default=1)
    args = parser.parse_args()
    from playwright.sync_api import sync_playwright

    trees = [("this tree", ROOT)] + ([("base", args.base.resolve())] if args.base else [])
    load = os.getloadavg()
    rows: list[tuple[str, dict]] = []
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        for _ in range(args.rounds):
            for name, tree in trees:
                rows.append((name, measure(browser, tree, args)))
                print(name, {k: v for k, v in rows[-1][1].items() if k != "budget"}, flush=True)
        browser.close()

    beside = " beside the demo session" if args.demo else ""
    title = (
        f"page streaming, {args.width}x{args.height} at pixel ratio {args.pixel_ratio:g},"
        f" headless chromium (SwiftShader), {args.mode}{beside},"
        f" {args.seconds:.0f} s per run, load average {load[0]:.1f} on {os.cpu_count()} cores"
    )
    table = Table(title=title)
    columns = ("code", "frames/s sent", "target", "", "poses/s", "latency ms", "server ms",
               "held %", "page ms/frame", "script ms/frame", "draw JS ms/frame", "draws/s",
               "send+recv ms/frame", "chromium cores", "server cores", "pixel ratio",
               "HUD says")  # fmt: skip
    for column in columns:
        table.add_column(column)
    for name, r in rows:
        table.add_row(
            name,
            f"{r['sent_fps']:.1f}",
            f">= {TARGET_FPS:.0f}",
            "✓" if r["sent_fps"] >= TARGET_FPS else "✗",
            f"{r['pose_fps']:.1f}",
            f"{r['latency_ms']:.0f}",
            f"{r['server_ms']:.0f}",
            f"{100 * r['held']:.0f}",
            f"{r['page_ms']:.0f}",
            f"{r['script_ms']:.0f}",
            f"{r['render_ms']:.1f}",
            f"{r['renders_per_s']:.1f}",
            (
                f"{r['kinds_ms'].get('send', 0):.1f}+{r['kinds_ms'].get('receive', 0):.1f}"
                if r["kinds_ms"]
                else "—"
            ),
            f"{r['browser_cores']:.2f}",
            f"{r['server_cores']:.2f}",
            f"{r['pixel_ratio']:g}",
            r["hud"] or "—",
        )
    console = Console(record=True, width=240)
    console.print(table)
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    heading = run_heading(utc_stamp(), f"; base: {args.base}" if args.base else "")
    with RESULTS.open("a") as out:
        out.write("\n".join(heading) + "\n```\n" + console.export_text() + "```\n")


if __name__ == "__main__":
    main()
