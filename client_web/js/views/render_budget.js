// How much drawing the page can afford: the pixel ratio the three.js views render at and how
// often they draw, adapted to what their draws cost here, so that a weak GPU (or WebGL in
// software, as in headless chromium) slows the views, never the stream. The stream shares the
// main thread with the draws: every millisecond a draw takes is one a pose waits before it is
// handled and the next frame goes out.
//
// - Pixel ratio: the device's (at most 2), at most 1 where WebGL runs in software
//   (SwiftShader, llvmpipe: every pixel is drawn by the CPU the server may need too). Each
//   RENDER_BUDGET.windowMs the mean draw time is held to frameMs: over it two windows in a
//   row, the ratio drops a step (down to minRatio); far under it for a few windows, it rises a
//   step again (each change reallocates every view's drawing buffer: not on one slow window).
// - Draw interval: RENDER_BUDGET.drawMs between draws normally (softwareDrawMs in software:
//   each draw also recomposites the page on the CPU); at least slowDrawMs while the stream runs
//   behind its rate, whatever it waits for (ui/hud.js): a phone's camera and a server on the
//   same machine come before the rotors' spin. The interval adapts: each overWindows windows
//   in a row that end with the stream behind double it (up to maxDrawMs), each calmWindows
//   windows at rate halve it again (down to the normal one), so the views draw as often as
//   the stream leaves room for. (In software WebGL a draw's pixels cost far more in the GPU
//   process than its JavaScript: benchmarks/page_stream.py splits chromium's CPU by process.)
// - Resizing a view's drawing buffer reallocates it (tens to hundreds of milliseconds in
//   software): a view keeps drawing into the old buffer, stretched by CSS, until its size has
//   been still for settleMs (fitRenderer).
//
// `?frameBudgetMs=N` overrides frameMs (the tests use a tiny one to see the ratio drop).

export const RENDER_BUDGET = Object.freeze({
  frameMs: 12, // mean JavaScript time of one draw the page affords
  windowMs: 1000, // how often the ratio is reconsidered
  step: 0.75, // the ratio's factor per step down (its inverse up)
  minRatio: 0.5,
  softwareMaxRatio: 1,
  calmWindows: 3, // windows far under budget before a step up
  drawMs: 33, // least time between draws of a view
  softwareDrawMs: 50, // the same where WebGL runs in software
  slowDrawMs: 100, // the same while the stream runs behind its rate
  maxDrawMs: 800, // the longest the adapted interval grows to
  overWindows: 2, // windows over budget before a step down
  settleMs: 300, // a new size must hold this long before the drawing buffer follows
});

/** Whether a three.js renderer's WebGL runs on the CPU (SwiftShader, llvmpipe, Mesa software). */
export function softwareWebGL(renderer) {
  const gl = renderer.getContext();
  const info = gl.getExtension("WEBGL_debug_renderer_info");
  const name = info ? gl.getParameter(info.UNMASKED_RENDERER_WEBGL) : gl.getParameter(gl.RENDERER);
  return /swiftshader|llvmpipe|softpipe|software/i.test(String(name));
}

export class RenderBudget {
  /**
   * @param {{frameMs?: number, devicePixelRatio?: number, software?: boolean}} options
   */
  constructor({ frameMs = RENDER_BUDGET.frameMs, devicePixelRatio = window.devicePixelRatio || 1, software = false } = {}) {
    this.frameMs = frameMs;
    this.maxRatio = Math.min(devicePixelRatio, 2, software ? RENDER_BUDGET.softwareMaxRatio : 2);
    this.pixelRatio = this.maxRatio;
    this.software = software;
    this.streamBehind = false; // set by the app: the stream runs behind its rate (ui/hud.js)
    this.intervalMs = this.baseDrawMs; // the adapted least time between draws
    this.behindWindows = 0; // windows in a row that ended with the stream behind
    this.atRateWindows = 0; // ... at its rate
    this.windowStart = performance.now();
    this.drawMsSum = 0;
    this.draws = 0;
    this.calm = 0;
    this.over = 0;
    this.lastWindow = { draws: 0, meanMs: 0 };
    this.changes = 0; // pixel ratio changes (tests, debugging)
  }

  /** The draw interval with the stream at rate, ms. */
  get baseDrawMs() {
    return this.software ? RENDER_BUDGET.softwareDrawMs : RENDER_BUDGET.drawMs;
  }

  /** Least time between two draws of a view, ms. */
  get drawIntervalMs() {
    return this.streamBehind ? Math.max(RENDER_BUDGET.slowDrawMs, this.intervalMs) : this.intervalMs;
  }

  /** Adapt the draw interval to the stream at a window's end (see the top of this file). */
  #adaptInterval() {
    if (this.streamBehind) {
      this.atRateWindows = 0;
      if (++this.behindWindows >= RENDER_BUDGET.overWindows) {
        this.behindWindows = 0;
        this.intervalMs = Math.min(RENDER_BUDGET.maxDrawMs, Math.max(RENDER_BUDGET.slowDrawMs, this.intervalMs * 2));
      }
    } else {
      this.behindWindows = 0;
      if (++this.atRateWindows >= RENDER_BUDGET.calmWindows) {
        this.atRateWindows = 0;
        this.intervalMs = Math.max(this.baseDrawMs, this.intervalMs / 2);
      }
    }
  }

  /** Time a draw: fn's JavaScript time counts against the budget (and `meter`, the page's load). */
  draw(fn, meter = null) {
    const t0 = performance.now();
    try {
      return fn();
    } finally {
      const ms = performance.now() - t0;
      this.drawMsSum += ms;
      this.draws += 1;
      meter?.add("draw", ms, t0);
    }
  }

  /** Reconsider the pixel ratio once a window has passed; cheap to call every animation frame. */
  update(now = performance.now()) {
    if (now - this.windowStart < RENDER_BUDGET.windowMs) return;
    const meanMs = this.draws ? this.drawMsSum / this.draws : 0;
    this.lastWindow = { draws: this.draws, meanMs };
    this.windowStart = now;
    this.drawMsSum = 0;
    this.draws = 0;
    this.#adaptInterval();
    if (!this.lastWindow.draws) return;
    let ratio = this.pixelRatio;
    if (meanMs > this.frameMs) {
      this.calm = 0;
      if (++this.over >= RENDER_BUDGET.overWindows) {
        ratio = Math.max(RENDER_BUDGET.minRatio, ratio * RENDER_BUDGET.step);
        this.over = 0;
      }
    } else {
      this.over = 0;
      if (meanMs < this.frameMs / 3 && ++this.calm >= RENDER_BUDGET.calmWindows) {
        ratio = Math.min(this.maxRatio, ratio / RENDER_BUDGET.step);
        this.calm = 0;
      }
    }
    ratio = Math.round(ratio * 100) / 100;
    if (ratio !== this.pixelRatio) {
      this.pixelRatio = ratio;
      this.changes += 1;
    }
  }

  summary() {
    return { pixelRatio: this.pixelRatio, maxRatio: this.maxRatio, software: this.software, frameMs: this.frameMs,
      drawIntervalMs: this.drawIntervalMs, lastWindow: { ...this.lastWindow }, changes: this.changes };
  }
}

/**
 * Size a renderer's drawing buffer to cssWidth x cssHeight at `ratio`, without touching the
 * canvas's CSS size (the view's stylesheet or layout sets it). A changed CSS size is applied
 * once it has held for RENDER_BUDGET.settleMs (a view whose container jiggles keeps its buffer);
 * the first size and a changed ratio at once. `state` is the view's own object between calls.
 * @returns {boolean} whether the buffer was resized
 */
export function fitRenderer(renderer, state, cssWidth, cssHeight, ratio, now = performance.now()) {
  if (!cssWidth || !cssHeight) return false;
  if (state.wantW !== cssWidth || state.wantH !== cssHeight) {
    state.wantW = cssWidth;
    state.wantH = cssHeight;
    state.wantSince = now;
  }
  const sized = state.w !== undefined;
  const sameSize = state.w === cssWidth && state.h === cssHeight;
  if (sameSize && state.ratio === ratio) return false;
  if (sized && !sameSize && state.ratio === ratio && now - state.wantSince < RENDER_BUDGET.settleMs) return false;
  renderer.setPixelRatio(ratio);
  renderer.setSize(cssWidth, cssHeight, false);
  Object.assign(state, { w: cssWidth, h: cssHeight, ratio });
  return true;
}
