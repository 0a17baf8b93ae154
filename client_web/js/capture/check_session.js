// The device check's AR session (check.html): a few seconds of immersive-ar measured the way
// live AR uses it (sources/live.js): the page's own XRWebGLLayer as the session's baseLayer
// (never the WebXR Layers path, where getCameraImage crashes Chrome 147+ on some phones), its
// own XRWebGLBinding, the camera texture read back through a framebuffer blit, depth from
// getDepthInformation. Plain WebGL2, no three.js: what fails here fails in this browser, not
// in a library. Every exception is kept with its name and message (#attempt), never swallowed.

import { flipRows, intrinsicsFromProjection } from "./packing.js";

export const MEASURE_MS = 3000; // the measurement, from the first XR frame
// Depth from motion may take a while: without any depth after MEASURE_MS the session goes on
// until the first depth image or this long (live AR gives up after 10 s, FIRST_DEPTH_TIMEOUT_MS).
export const MAX_MS = 10000;
const HASH_SIZE = 16; // camera images are told apart by a 16x16 read-back
const UPRIGHT_LONG_SIDE = 240; // the picture shown for the upright test

/** What the check asks for: only "local" required, so that a phone lacking depth or camera
 * access still starts a session and reports the rest. */
export function sessionOptions(overlayRoot) {
  return {
    requiredFeatures: ["local"],
    optionalFeatures: ["depth-sensing", "camera-access", "dom-overlay"],
    depthSensing: {
      usagePreference: ["cpu-optimized", "gpu-optimized"],
      dataFormatPreference: ["luminance-alpha", "unsigned-short", "float32"],
    },
    domOverlay: { root: overlayRoot },
  };
}

/** FNV-1a over bytes: enough to tell one image from the next. */
function fnv1a(bytes) {
  let h = 0x811c9dc5;
  for (let i = 0; i < bytes.length; i++) h = Math.imul(h ^ bytes[i], 0x01000193);
  return h >>> 0;
}

const round = (v, digits = 2) => Number(v.toFixed(digits));

export class SessionProbe {
  /**
   * @param {XRSession} session started from the user's tap
   * @param {(where: string, exc: unknown) => void} recordError the report's error list
   * @param {(elapsedMs: number, probe: SessionProbe) => void} onProgress once per XR frame
   */
  constructor(session, recordError, onProgress) {
    this.session = session;
    this.recordError = recordError;
    this.onProgress = onProgress;
    this.failing = new Set(); // APIs that threw once: not called again
    this.t0 = null;
    this.xr = { frames: 0, framesWithPose: 0, viewCount: null, baseLayerIsXRWebGLLayer: null };
    this.camera = { frames: 0, distinct: 0, width: null, height: null, readMs: 0, reads: 0, lastHash: null, readBack: null };
    this.depth = { frames: 0, distinct: 0, firstAtMs: null, cameraImagesSinceFirst: 0, lastHash: null, width: null,
      height: null, rawValueToMeters: null, normDepthBufferFromNormView: null, zeroFraction: null };
    this.view = null; // projection, viewport, framebuffer, intrinsics of the first view
    this.uprightImage = null; // the last camera image read back (ImageData, top row first)
    this.endedEarlyMs = null;
  }

  /** Set up the layer and binding, run the frames, end the session: resolves with the result
   * (see #result) once the session has ended. */
  async run() {
    const session = this.session;
    const ended = new Promise((resolve) => session.addEventListener("end", resolve, { once: true }));
    const canvas = document.createElement("canvas");
    const gl = canvas.getContext("webgl2", { xrCompatible: true, alpha: true, antialias: false });
    if (!gl) throw new Error("no WebGL2 context");
    this.gl = gl;
    if (gl.getContextAttributes().xrCompatible !== true) await gl.makeXRCompatible();
    this.layer = new XRWebGLLayer(session, gl, { alpha: true, depth: false, antialias: false });
    session.updateRenderState({ baseLayer: this.layer });
    this.binding = this.#attempt("new XRWebGLBinding", () => new XRWebGLBinding(session, gl));
    this.space = await session.requestReferenceSpace("local");
    this.features = session.enabledFeatures ? [...session.enabledFeatures] : null;
    // Without enabledFeatures (older browsers) each API is tried and its exception kept.
    this.depthEnabled = this.features ? this.features.includes("depth-sensing") : true;
    this.finished = false;
    session.requestAnimationFrame(this.#loop);
    await ended;
    if (!this.finished && this.t0 !== null) this.endedEarlyMs = round(this.lastTime - this.t0, 0);
    return this.#result();
  }

  #attempt(where, fn) {
    if (this.failing.has(where)) return null;
    try {
      return fn();
    } catch (exc) {
      this.failing.add(where);
      this.recordError(where, exc);
      return null;
    }
  }

  #loop = (time, frame) => {
    if (this.finished) return;
    this.session.requestAnimationFrame(this.#loop);
    this.t0 ??= time;
    this.lastTime = time;
    this.xr.frames += 1;
    const layer = this.session.renderState.baseLayer;
    this.xr.baseLayerIsXRWebGLLayer = layer instanceof XRWebGLLayer;
    this.#attempt("clear the XR layer", () => this.#clear());
    const pose = this.#attempt("getViewerPose", () => frame.getViewerPose(this.space));
    const elapsed = time - this.t0;
    let cameraNow = false;
    if (pose) {
      this.xr.framesWithPose += 1;
      this.xr.viewCount = pose.views.length;
      const view = pose.views[0];
      if (!this.view) this.#attempt("the view's geometry", () => this.#describeView(view));
      if (this.depthEnabled) this.#attempt("getDepthInformation", () => this.#readDepth(frame, view, time));
      cameraNow = Boolean(view.camera) && this.#attempt("getCameraImage", () => this.#readCamera(view, time)) === true;
      // Done after MEASURE_MS once depth has come (or never will: MAX_MS), on a frame whose
      // camera image is then kept for the upright test.
      const noDepth = !this.depthEnabled || this.failing.has("getDepthInformation");
      const noCamera = this.camera.frames === 0 || this.failing.has("getCameraImage");
      const measured = elapsed >= MEASURE_MS && (this.depth.frames > 0 || noDepth);
      if ((measured && (cameraNow || noCamera)) || elapsed >= MAX_MS) {
        if (cameraNow) this.#attempt("camera image read-back", () => this.#keepUprightImage(view));
        this.#finish();
      }
    } else if (elapsed >= MAX_MS) {
      this.#finish();
    }
    this.onProgress(elapsed, this);
  };

  #finish() {
    this.finished = true;
    this.durationMs = round(this.lastTime - this.t0, 0);
    this.session.end().catch((exc) => this.recordError("session.end", exc));
  }

  /** The layer is the page's overlay over the camera: transparent, nothing drawn. */
  #clear() {
    const gl = this.gl;
    gl.bindFramebuffer(gl.FRAMEBUFFER, this.layer.framebuffer);
    gl.viewport(0, 0, this.layer.framebufferWidth, this.layer.framebufferHeight);
    gl.clearColor(0, 0, 0, 0);
    gl.clear(gl.COLOR_BUFFER_BIT);
  }

  #describeView(view) {
    const viewport = this.layer.getViewport(view);
    const [fx, fy, cx, cy] = intrinsicsFromProjection(view.projectionMatrix, viewport.width, viewport.height);
    this.view = {
      projectionMatrix: Array.from(view.projectionMatrix, (v) => round(v, 6)),
      viewport: { x: viewport.x, y: viewport.y, width: viewport.width, height: viewport.height },
      framebuffer: [this.layer.framebufferWidth, this.layer.framebufferHeight],
      // Pinhole intrinsics at the viewport's size (pixel centres at integers), as live AR sends.
      intrinsics: { fx: round(fx), fy: round(fy), cx: round(cx), cy: round(cy), width: viewport.width, height: viewport.height },
    };
  }

  #readDepth(frame, view, time) {
    const cpu = this.session.depthUsage !== "gpu-optimized";
    const info = cpu ? frame.getDepthInformation(view) : this.binding?.getDepthInformation(view);
    if (!info) return; // Chrome: no new ARCore depth image in this frame, or none yet
    const d = this.depth;
    d.frames += 1;
    if (d.firstAtMs === null) {
      d.firstAtMs = round(time - this.t0, 0);
      d.firstTime = time;
    }
    d.width = info.width;
    d.height = info.height;
    d.rawValueToMeters = info.rawValueToMeters;
    d.normDepthBufferFromNormView = Array.from(info.normDepthBufferFromNormView.matrix, (v) => round(v, 6));
    if (!cpu) return; // a GPU texture: counted, not read
    const values = this.session.depthDataFormat === "float32" ? new Float32Array(info.data) : new Uint16Array(info.data);
    let zeros = 0;
    for (let i = 0; i < values.length; i++) if (!(values[i] > 0)) zeros += 1;
    d.zeroFraction = round(zeros / values.length, 3);
    const hash = fnv1a(new Uint8Array(values.buffer, values.byteOffset, values.byteLength));
    if (hash !== d.lastHash) d.distinct += 1;
    d.lastHash = hash;
  }

  /** Count this frame's camera image, and whether it is a new one (its 16x16 read-back
   * differs from the last): true when the frame had one. The read-back is synchronous and
   * its time is reported (camera.readMsMean): it may cost the XR frame rate a little. */
  #readCamera(view, time) {
    const c = this.camera;
    const texture = this.binding.getCameraImage(view.camera);
    c.frames += 1;
    c.width = view.camera.width;
    c.height = view.camera.height;
    if (this.failing.has("camera image read-back")) return true;
    const started = performance.now();
    const pixels = this.#attempt("camera image read-back", () => this.#readTexture(texture, [c.width, c.height], HASH_SIZE, HASH_SIZE));
    c.readMs += performance.now() - started;
    c.reads += 1;
    if (!pixels) return true;
    const hash = fnv1a(pixels);
    if (hash !== c.lastHash) {
      c.distinct += 1;
      if (this.depth.firstTime !== undefined && time >= this.depth.firstTime) this.depth.cameraImagesSinceFirst += 1;
    }
    c.lastHash = hash;
    return true;
  }

  #keepUprightImage(view) {
    const texture = this.binding.getCameraImage(view.camera);
    const { width, height } = view.camera;
    const scale = UPRIGHT_LONG_SIDE / Math.max(width, height);
    const [w, h] = [Math.max(1, Math.round(width * scale)), Math.max(1, Math.round(height * scale))];
    const pixels = this.#readTexture(texture, [width, height], w, h);
    this.uprightImage = new ImageData(flipRows(pixels, w, h), w, h); // GL rows are bottom-up
  }

  /** The camera texture (width x height) blitted down to w x h and read back (rows
   * bottom-up), as live AR reads it; a texture that cannot be a framebuffer's attachment, or a failed blit, throws. */
  #readTexture(texture, [width, height], w, h) {
    const gl = this.gl;
    this.readFb ??= gl.createFramebuffer();
    this.targets ??= new Map();
    const key = `${w}x${h}`;
    if (!this.targets.has(key)) {
      const fb = gl.createFramebuffer();
      const rb = gl.createRenderbuffer();
      gl.bindRenderbuffer(gl.RENDERBUFFER, rb);
      gl.renderbufferStorage(gl.RENDERBUFFER, gl.RGBA8, w, h);
      gl.bindFramebuffer(gl.FRAMEBUFFER, fb);
      gl.framebufferRenderbuffer(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.RENDERBUFFER, rb);
      this.targets.set(key, fb);
    }
    const target = this.targets.get(key);
    try {
      gl.bindFramebuffer(gl.READ_FRAMEBUFFER, this.readFb);
      gl.framebufferTexture2D(gl.READ_FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, texture, 0);
      const status = gl.checkFramebufferStatus(gl.READ_FRAMEBUFFER);
      if (status !== gl.FRAMEBUFFER_COMPLETE) {
        throw new Error(`the camera texture is no complete framebuffer attachment (status 0x${status.toString(16)})`);
      }
      gl.bindFramebuffer(gl.DRAW_FRAMEBUFFER, target);
      gl.getError(); // clear older errors: the next check is the blit's
      gl.blitFramebuffer(0, 0, width, height, 0, 0, w, h, gl.COLOR_BUFFER_BIT, gl.LINEAR);
      const error = gl.getError();
      if (error !== gl.NO_ERROR) throw new Error(`blit of the camera texture failed (GL error 0x${error.toString(16)})`);
      gl.bindFramebuffer(gl.READ_FRAMEBUFFER, target);
      const pixels = new Uint8Array(w * h * 4);
      gl.readPixels(0, 0, w, h, gl.RGBA, gl.UNSIGNED_BYTE, pixels);
      return pixels;
    } finally {
      gl.bindFramebuffer(gl.READ_FRAMEBUFFER, null);
      gl.bindFramebuffer(gl.DRAW_FRAMEBUFFER, null);
    }
  }

  /** The measurements, as the report holds them (rates per second of XR time). */
  #result() {
    const seconds = (this.durationMs ?? this.endedEarlyMs ?? 0) / 1000;
    const perSecond = (n, s = seconds) => (s > 0 ? round(n / s, 1) : null);
    const c = this.camera;
    const d = this.depth;
    const depthSeconds = d.firstAtMs === null ? 0 : seconds - d.firstAtMs / 1000;
    return {
      enabledFeatures: this.features,
      depthUsage: this.session.depthUsage ?? null,
      depthDataFormat: this.session.depthDataFormat ?? null,
      domOverlay: this.session.domOverlayState?.type ?? null,
      environmentBlendMode: this.session.environmentBlendMode ?? null,
      durationMs: this.durationMs ?? null,
      endedEarlyMs: this.endedEarlyMs,
      baseLayerIsXRWebGLLayer: this.xr.baseLayerIsXRWebGLLayer,
      xr: { frames: this.xr.frames, fps: perSecond(this.xr.frames), framesWithPose: this.xr.framesWithPose, viewCount: this.xr.viewCount },
      view: this.view,
      camera: {
        framesWithImage: c.frames, distinctImages: c.distinct, fps: perSecond(c.distinct), width: c.width, height: c.height,
        readMsMean: c.reads ? round(c.readMs / c.reads) : null,
        uprightImageSize: this.uprightImage ? [this.uprightImage.width, this.uprightImage.height] : null,
      },
      depth: {
        frames: d.frames, distinctImages: d.distinct, firstAfterMs: d.firstAtMs, fps: perSecond(d.distinct, depthSeconds),
        // Depth images per new camera image once depth flows (Chrome: 1/2 or 1/3 typically).
        perCameraImage: d.cameraImagesSinceFirst ? round(d.distinct / d.cameraImagesSinceFirst) : null,
        width: d.width, height: d.height, rawValueToMeters: d.rawValueToMeters,
        normDepthBufferFromNormView: d.normDepthBufferFromNormView, zeroFraction: d.zeroFraction,
      },
    };
  }
}
