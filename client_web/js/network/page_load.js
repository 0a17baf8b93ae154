// The page's own work on the main thread, by kind (draw, capture, receive), over the last
// PAGE_LOAD_WINDOW_MS, and what a streamed frame waits for: the server (its own time per frame,
// pose.timings_ms.server_total), the page (from the pose back to the next frame sent, and the
// part of the round trip the pose spent waiting for a busy main thread), or the network (the
// rest of the round trip). The HUD names the largest when the stream runs behind its rate.

export const PAGE_LOAD_WINDOW_MS = 2000;

/** The mean of numbers (NaN for none). */
export function mean(values) {
  return values.length ? values.reduce((a, b) => a + b, 0) / values.length : NaN;
}

/**
 * What one streamed frame waited for, from measured times (all ms, per frame).
 * @param {{periodMs: number, latencyMs: number, serverMs: number, busyFraction: number}} t
 *   periodMs: between frames sent; latencyMs: sent to pose back (mean); serverMs: the
 *   server's own part (mean server_total); busyFraction: the main thread's share spent on
 *   the page's own work
 * @returns {{server: number, page: number, network: number, name: "server"|"page"|"network"}}
 */
export function waitsFor({ periodMs, latencyMs, serverMs, busyFraction }) {
  const server = Math.max(0, serverMs);
  const rest = Math.max(0, latencyMs - server); // transit both ways, and the pose in the page's queue
  const busy = Math.min(1, Math.max(0, busyFraction));
  const gap = Math.max(0, periodMs - latencyMs); // pose back -> next frame out: the page's
  const parts = { server, page: gap + rest * busy, network: rest * (1 - busy) };
  const name = Object.keys(parts).reduce((a, b) => (parts[b] > parts[a] ? b : a));
  return { ...parts, name };
}

export class PageLoad {
  constructor(windowMs = PAGE_LOAD_WINDOW_MS) {
    this.windowMs = windowMs;
    this.entries = []; // [at, kind, ms]
  }

  /** Record `ms` of main-thread work of `kind` that started at `at`. */
  add(kind, ms, at = performance.now()) {
    this.entries.push([at, kind, ms]);
    if (this.entries.length > 4096) this.entries.splice(0, 1024);
  }

  /** Run fn, counting its time as `kind`. */
  time(kind, fn) {
    const t0 = performance.now();
    try {
      return fn();
    } finally {
      this.add(kind, performance.now() - t0, t0);
    }
  }

  /** Work in the window up to `now`: {ms by kind, total ms, fraction of the window, top kind}. */
  summary(now = performance.now()) {
    while (this.entries.length && this.entries[0][0] < now - this.windowMs) this.entries.shift();
    const byKind = {};
    for (const [, kind, ms] of this.entries) byKind[kind] = (byKind[kind] ?? 0) + ms;
    const total = Object.values(byKind).reduce((a, b) => a + b, 0);
    const top = Object.keys(byKind).reduce((a, b) => (byKind[b] > (byKind[a] ?? -1) ? b : a), null);
    return { byKind, total, fraction: Math.min(1, total / this.windowMs), top };
  }
}
