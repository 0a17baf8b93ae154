"""Rendering cost of the phone page: frames per second in headless chromium on a phone-sized
viewport, while the page replays the small demo into a real server and the drone hovers.

Cases, measured one after the other in one page (the replay streams throughout):

- ``AR + occlusion``: the AR view with occlusion on (the frame's depth as occluder);
- ``AR, no occlusion``: the same with occlusion off, for comparison;
- ``FPV``: the drone's camera drawn from the fused mesh.

For each, over ``--seconds`` (10): the page's frame rate from ``requestAnimationFrame``
timestamps (frames per second and the 95th percentile frame interval), how often the view
itself was drawn (the page draws AR and FPV at most every 33 ms, and only when something
changed) and the JavaScript time per draw. The target is >= 30 fps (rAF). Chromium runs as the
tests run it: Debian's chromium with SwiftShader (software WebGL, on the CPU), so the figures are
a CPU-bound lower bound for a phone's GPU; the load average at the start is printed beside them.
Appends the table to ``benchmarks/results/page_fps.md``.

    python benchmarks/page_fps.py [--seconds S] [--width 412 --height 915]
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import tempfile
from pathlib import Path

from rich.console import Console
from rich.table import Table

from server.client.server_process import ServerProcess

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results" / "page_fps.md"
CHROMIUM = Path(os.environ.get("DRONESIM_CHROMIUM", "/usr/bin/chromium"))
CHROMIUM_ARGS = [  # as tests/support/browser.py: software WebGL, no GPU on these machines
    "--no-sandbox",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--ignore-gpu-blocklist",
    "--disable-dev-shm-usage",
]
TARGET_FPS = 30.0

# Count the view's draws and their JavaScript time, and every animation frame, for `ms`.
MEASURE_JS = """async ([view, ms]) => {
  const target = view === 'fpv' ? window.dronesim.fpv : window.dronesim.ar;
  const original = target.render;
  let draws = 0, drawMs = 0;
  target.render = function (...args) {
    const t0 = performance.now();
    const out = original.apply(this, args);
    drawMs += performance.now() - t0;
    draws += 1;
    return out;
  };
  const stamps = [];
  await new Promise((resolve) => {
    const t0 = performance.now();
    const frame = (now) => {
      stamps.push(now);
      if (now - t0 < ms) requestAnimationFrame(frame); else resolve();
    };
    requestAnimationFrame(frame);
  });
  target.render = original;
  const gaps = stamps.slice(1).map((t, i) => t - stamps[i]).sort((a, b) => a - b);
  const span = (stamps.at(-1) - stamps[0]) / 1000;
  return { fps: (stamps.length - 1) / span, p95: gaps[Math.floor(0.95 * (gaps.length - 1))],
    drawsPerS: draws / span, msPerDraw: draws ? drawMs / draws : 0,
    occlusion: window.dronesim.ar.lastDraw.occlusion,
    triangles: window.dronesim.fpv.lastDraw.triangles, mesh: window.dronesim.mapMesh.summary() };
}"""


def measure(page, view: str, seconds: float) -> dict:
    return page.evaluate(MEASURE_JS, [view, seconds * 1000])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--width", type=int, default=412)
    parser.add_argument("--height", type=int, default=915)
    args = parser.parse_args()
    from playwright.sync_api import sync_playwright

    load = os.getloadavg()
    rows = []
    with tempfile.TemporaryDirectory() as tmp, ServerProcess(Path(tmp)) as server:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
            context = browser.new_context(
                viewport={"width": args.width, "height": args.height},
                is_mobile=True,
                has_touch=True,
                device_scale_factor=1,
            )
            page = context.new_page()
            page.goto(f"{server.url}/?mode=demo-small&view=ar")
            page.wait_for_function("window.dronesim && window.dronesim.pilot", timeout=30_000)
            page.tap("#btn-stream")
            page.wait_for_function(
                "window.dronesim.seen.poses >= 30 && window.dronesim.seen.lastDrone"
                " && window.dronesim.ar.lastDraw.occlusion === 'depth'",
                timeout=120_000,
            )
            rows.append(("AR + occlusion", measure(page, "ar", args.seconds)))
            page.tap("#btn-occlusion")
            rows.append(("AR, no occlusion", measure(page, "ar", args.seconds)))
            page.tap("#btn-occlusion")
            page.tap("[data-view=fpv]")
            page.wait_for_function("window.dronesim.snapshot().fpv.drawn", timeout=60_000)
            rows.append(("FPV", measure(page, "fpv", args.seconds)))
            browser.close()

    title = (
        f"page fps, {args.width}x{args.height} headless chromium (SwiftShader),"
        f" {args.seconds:.0f} s per case, load average {load[0]:.1f} on {os.cpu_count()} cores"
    )
    table = Table(title=title)
    for column in (
        "case",
        "fps (rAF)",
        "target",
        "",
        "p95 frame ms",
        "draws/s",
        "JS ms/draw",
        "note",
    ):
        table.add_column(column)
    for name, r in rows:
        mesh = r["mesh"]["lastDownload"] or {"ms": float("nan"), "bytes": 0}
        note = (
            f"occluder: {r['occlusion']}"
            if name.startswith("AR")
            else f"{r['triangles']} triangles; mesh.ply {mesh['bytes'] / 1e6:.1f} MB"
            f" in {mesh['ms']:.0f} ms"
        )
        table.add_row(
            name,
            f"{r['fps']:.1f}",
            f">= {TARGET_FPS:.0f}",
            "✓" if r["fps"] >= TARGET_FPS else "✗",
            f"{r['p95']:.1f}",
            f"{r['drawsPerS']:.1f}",
            f"{r['msPerDraw']:.1f}",
            note,
        )
    console = Console(record=True, width=140)
    console.print(table)
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    stamp = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
    with RESULTS.open("a") as out:
        out.write(
            f"\n## {stamp}, {platform.node()}, {platform.processor() or platform.machine()}\n\n"
        )
        out.write("```\n" + console.export_text() + "```\n")


if __name__ == "__main__":
    main()
