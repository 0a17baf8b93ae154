// An emulated WebXR AR device for the browser tests: what Chrome on an Android phone with ARCore
// gives a page, played from a recorded RGB-D sequence. Injected before the page's own scripts
// (Playwright add_init_script) after `window.__xrDeviceConfig` is set (tests/support/webxr_device.py).
//
// Modelled on the WebXR Device API, the Depth Sensing module (cpu-optimized; luminance-alpha and
// float32 buffers with rawValueToMeters and normDepthBufferFromNormView), Raw Camera Access
// (XRView.camera, XRWebGLBinding.getCameraImage) and Chrome's behaviour on ARCore:
// - an immersive-ar session only from a user's tap (SecurityError otherwise), one at a time; a
//   required feature the device lacks rejects the request with NotSupportedError, an optional
//   one is left out of enabledFeatures; depth-sensing needs the depthSensing preferences; a user
//   who refused the camera permission gets no camera-access (and permissions.query says
//   "denied");
// - frames at the display rate; the camera runs at the recording's rate; the depth buffer is a
//   small landscape image of the sensor (e.g. 160x90) whatever the screen's orientation, mapped
//   to the view through normDepthBufferFromNormView (a rotation for portrait);
// - the camera image is a WebGL texture valid during the frame, of Chrome's size: ARCore's
//   camera image turned into the view and cropped to its aspect (864x1920 on a 1080x2400
//   portrait view), not the view's; depth is uint16 (luminance-alpha or unsigned-short,
//   rawValueToMeters 0.001) and may only be read during the frame callback (InvalidStateError
//   after it); the sensor may be turned 0, 90, 180 or 270 degrees into the view;
// - some frames come without depth information or without a camera image (ARCore
//   re-initialising), and depth from motion is empty for the first second;
// - viewer poses are the phone's visual-inertial odometry: the recording's ground truth with
//   drift and noise, in a gravity-aligned "local" space (y up).
// Options that model today's Chrome more closely (config, from tests/support/webxr_device.py):
// - layersApi: Chrome 147+ has XRWebGLBinding.prototype.createProjectionLayer, so three.js's
//   WebXRManager renders into a projection layer and leaves renderState.baseLayer null; on such
//   a session getCameraImage crashes the tab on real phones (three.js issue #33404): here it
//   throws and counts the crash (state.crashes). The projection layer itself is a plain fake
//   (its textures are never shown), enough for three to take that path;
// - depthEvery n: getDepthInformation gives depth only on the XR frames that bring a new
//   ARCore depth image, here every n-th new camera frame, and null on the others (Chrome gives
//   no depth for a frame without a new depth image; depth comes slower than the camera);
// - depthAfterMoveM: null depth (not zeros) until the phone has moved this far from where the
//   session started (depth from motion); depthNever: no depth at all;
// - poseLost: recording frames on which ARCore is not tracking: the viewer pose is null (no
//   views, no camera image, no depth); the poses after such a stretch may jump (relocalised),
//   which tests/support/webxr_device.py writes into the poses.
// What is not modelled: hit tests, anchors, lighting, gpu-optimized depth, the compositor's
// latency, the reference space's reset event (not sent on a jump here).

(() => {
  const config = window.__xrDeviceConfig;
  if (!config) return;

  const AHEAD = 10; // recording frames loaded ahead of the one shown
  const LOADS = 3; // concurrent loads
  const IDENTITY = [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1];

  const domError = (name, message) => new DOMException(message, name);

  function invert(m) {
    // Rigid transform (column-major): R^T, -R^T t.
    const r = [m[0], m[4], m[8], m[1], m[5], m[9], m[2], m[6], m[10]];
    const t = [m[12], m[13], m[14]];
    return [
      r[0], r[1], r[2], 0, r[3], r[4], r[5], 0, r[6], r[7], r[8], 0,
      -(r[0] * t[0] + r[3] * t[1] + r[6] * t[2]),
      -(r[1] * t[0] + r[4] * t[1] + r[7] * t[2]),
      -(r[2] * t[0] + r[5] * t[1] + r[8] * t[2]), 1,
    ];
  }

  class EmulatedRigidTransform {
    constructor(matrix) {
      this.matrix = Float32Array.from(matrix);
      this.position = { x: matrix[12], y: matrix[13], z: matrix[14], w: 1 };
      const m = matrix; // rotation -> quaternion (Shepperd)
      const tr = m[0] + m[5] + m[10];
      let q;
      if (tr > 0) {
        const s = Math.sqrt(tr + 1) * 2;
        q = [(m[6] - m[9]) / s, (m[8] - m[2]) / s, (m[1] - m[4]) / s, s / 4];
      } else if (m[0] > m[5] && m[0] > m[10]) {
        const s = Math.sqrt(1 + m[0] - m[5] - m[10]) * 2;
        q = [s / 4, (m[4] + m[1]) / s, (m[8] + m[2]) / s, (m[6] - m[9]) / s];
      } else if (m[5] > m[10]) {
        const s = Math.sqrt(1 + m[5] - m[0] - m[10]) * 2;
        q = [(m[4] + m[1]) / s, s / 4, (m[9] + m[6]) / s, (m[8] - m[2]) / s];
      } else {
        const s = Math.sqrt(1 + m[10] - m[0] - m[5]) * 2;
        q = [(m[8] + m[2]) / s, (m[9] + m[6]) / s, s / 4, (m[1] - m[4]) / s];
      }
      this.orientation = { x: q[0], y: q[1], z: q[2], w: q[3] };
    }

    get inverse() {
      return new EmulatedRigidTransform(invert(this.matrix));
    }
  }

  /** The recording: its files loaded once (two bundles: JPEGs end to end, depth buffers of a
   * fixed size), camera images decoded a few frames ahead, shown in real time. */
  class Recording {
    constructor() {
      this.frames = new Map(); // index -> ImageBitmap, decoded
      this.decoding = new Set();
      this.failed = 0;
      this.ready = null;
    }

    load() {
      this.ready ??= Promise.all([
        fetch(`${config.base}/colour.bin`).then((r) => r.arrayBuffer()),
        fetch(`${config.base}/depth.bin`).then((r) => r.arrayBuffer()),
      ]).then(([colour, depth]) => {
        this.colour = colour;
        this.depthBytes = depth.byteLength / config.frames;
        this.depth = depth;
      });
      return this.ready;
    }

    depthOf(index) {
      return this.depth.slice(index * this.depthBytes, (index + 1) * this.depthBytes);
    }

    /** Decode frames from..from+AHEAD; release those before `shown`. */
    prefetch(from, shown) {
      for (const [i, bitmap] of this.frames) if (i < shown) {
        bitmap.close();
        this.frames.delete(i);
      }
      for (let i = from; i < Math.min(config.frames, from + AHEAD) && this.decoding.size < LOADS; i++) {
        if (this.frames.has(i) || this.decoding.has(i)) continue;
        this.decoding.add(i);
        const jpeg = new Blob([this.colour.slice(config.colourOffsets[i], config.colourOffsets[i + 1])], { type: "image/jpeg" });
        // Bottom row first, as GL textures hold images (texImage2D ignores UNPACK_FLIP_Y_WEBGL
        // for an ImageBitmap).
        createImageBitmap(jpeg, { imageOrientation: "flipY" }).then((bitmap) => this.frames.set(i, bitmap), (exc) => {
          this.failed += 1;
          console.warn(`emulated AR device: frame ${i} did not decode`, exc);
        }).finally(() => this.decoding.delete(i));
      }
    }

    /** The newest decoded frame at or before `due` (the camera stalls rather than skips ahead). */
    latest(due) {
      for (let i = due; i >= 0 && i >= due - AHEAD; i--) if (this.frames.has(i)) return i;
      return null;
    }
  }

  class EmulatedCamera {
    constructor(index) {
      this.width = config.cameraSize[0];
      this.height = config.cameraSize[1];
      this._index = index;
    }
  }

  class EmulatedView {
    constructor(index, hasCamera) {
      this.eye = "none";
      this.projectionMatrix = Float32Array.from(config.projection);
      this.transform = new EmulatedRigidTransform(config.poses[index]);
      this.recommendedViewportScale = null;
      this.camera = hasCamera ? new EmulatedCamera(index) : null;
      this._index = index;
    }

    requestViewportScale() {}
  }

  class EmulatedDepthInformation {
    constructor(frame, index, buffer) {
      this._frame = frame;
      this.width = config.depthSize[0];
      this.height = config.depthSize[1];
      this.rawValueToMeters = frame.session.depthDataFormat === "float32" ? 1.0 : 0.001;
      this.normDepthBufferFromNormView = new EmulatedRigidTransform(config.normDepthBufferFromNormView);
      this._buffer = buffer;
    }

    get data() {
      if (!this._frame._active) throw domError("InvalidStateError", "depth data read outside its XR frame");
      return this._buffer;
    }

    getDepthInMeters(x, y) {
      const m = config.normDepthBufferFromNormView;
      const u = m[0] * x + m[4] * y + m[12];
      const v = m[1] * x + m[5] * y + m[13];
      const col = Math.min(this.width - 1, Math.max(0, Math.floor(u * this.width)));
      const row = Math.min(this.height - 1, Math.max(0, Math.floor(v * this.height)));
      const values = this._frame.session.depthDataFormat === "float32" ? new Float32Array(this.data) : new Uint16Array(this.data);
      return values[row * this.width + col] * this.rawValueToMeters;
    }
  }

  class EmulatedFrame {
    constructor(session, index, time) {
      this.session = session;
      this.predictedDisplayTime = time;
      this._index = index;
      this._active = true;
      this._view = null;
    }

    getViewerPose(space) {
      if (!this._active) throw domError("InvalidStateError", "getViewerPose outside its XR frame");
      if (space._type === "viewer") return { transform: new EmulatedRigidTransform(IDENTITY), views: [], emulatedPosition: false };
      if (this.session._device.missing("pose", this._index)) return null; // ARCore is not tracking
      this._view ??= new EmulatedView(this._index, !this.session._device.missing("camera", this._index));
      return { transform: this._view.transform, views: [this._view], emulatedPosition: false };
    }

    getDepthInformation(view) {
      if (!this._active) throw domError("InvalidStateError", "getDepthInformation outside its XR frame");
      if (!this.session.enabledFeatures.includes("depth-sensing") || this.session.depthUsage !== "cpu-optimized") {
        throw domError("NotSupportedError", "depth sensing (cpu-optimized) is not enabled in this session");
      }
      const device = this.session._device;
      device.state.depthRequests += 1;
      if (device.missing("depth", view._index)) return null;
      if (config.depthNever || (config.depthEvery > 0 && !this._newDepth)) return null;
      if (config.depthAfterMoveM > 0 && !device.moved(view._index)) return null;
      if (!this._depthCounted) {
        this._depthCounted = true; // one depth image per frame, however often the page asks
        device.state.depthFrames += 1;
      }
      let buffer;
      if (this.predictedDisplayTime - device.t0 < config.emptyDepthS * 1000) {
        buffer = new ArrayBuffer(config.depthSize[0] * config.depthSize[1] * (this.session.depthDataFormat === "float32" ? 4 : 2));
      } else {
        buffer = device.recording.depthOf(view._index);
      }
      return new EmulatedDepthInformation(this, view._index, buffer);
    }
  }

  class EmulatedSession extends EventTarget {
    constructor(device, features, depthUsage, depthFormat, domOverlayRoot) {
      super();
      this._device = device;
      this.enabledFeatures = Object.freeze([...features]);
      this.depthUsage = depthUsage;
      this.depthDataFormat = depthFormat;
      this.environmentBlendMode = "alpha-blend";
      this.interactionMode = "screen-space";
      this.visibilityState = "visible";
      this.inputSources = [];
      this.domOverlayState = domOverlayRoot ? { type: "screen" } : null;
      this.renderState = { baseLayer: null, layers: [], depthNear: 0.1, depthFar: 1000, inlineVerticalFieldOfView: null };
      this._pending = null;
      this._callbacks = [];
      this._nextHandle = 1;
      this._ended = false;
    }

    updateRenderState(state = {}) {
      if (this._ended) throw domError("InvalidStateError", "the session has ended");
      if (state.baseLayer && state.layers) throw domError("NotSupportedError", "baseLayer and layers set together");
      if (state.layers && !config.layersApi) throw domError("NotSupportedError", "this device has no WebXR layers");
      // A base layer and a layer list replace each other (WebXR Layers: one or the other).
      if (state.layers) state = { ...state, baseLayer: null };
      if (state.baseLayer) state = { ...state, layers: [] };
      this._pending = { ...(this._pending ?? {}), ...state }; // applied at the next frame
    }

    async requestReferenceSpace(type) {
      if (!["viewer", "local", "local-floor"].includes(type)) throw domError("NotSupportedError", `reference space ${type}`);
      if (type !== "viewer" && !this.enabledFeatures.includes(type)) throw domError("NotSupportedError", `${type} not enabled`);
      const space = new EventTarget();
      space._type = type;
      space.getOffsetReferenceSpace = () => space;
      return space;
    }

    requestAnimationFrame(callback) {
      const handle = this._nextHandle++;
      this._callbacks.push({ handle, callback });
      return handle;
    }

    cancelAnimationFrame(handle) {
      this._callbacks = this._callbacks.filter((c) => c.handle !== handle);
    }

    async end() {
      if (this._ended) return;
      this._ended = true;
      this._device.sessionEnded(this);
      const event = new Event("end");
      event.session = this;
      this.dispatchEvent(event);
    }

    _frame(time, index, newDepth) {
      if (this._pending) {
        Object.assign(this.renderState, this._pending);
        this._pending = null;
      }
      const callbacks = this._callbacks;
      this._callbacks = [];
      const frame = new EmulatedFrame(this, index, time);
      frame._newDepth = newDepth;
      for (const { callback } of callbacks) {
        try {
          callback(time, frame);
        } catch (exc) {
          setTimeout(() => { throw exc; }); // reported as the browser would, the loop goes on
        }
      }
      frame._active = false;
    }
  }

  /** The device: the session's clock, the recording, the camera texture. */
  class Device {
    constructor() {
      this.recording = new Recording();
      this.session = null;
      this.log = []; // [time ms, recording frame] of every XR frame
      // cameraFrames: XR frames that brought a new camera image; depthFrames: XR frames that gave
      // depth; poseLost: XR frames without a viewer pose; crashes: getCameraImage calls that
      // would have crashed the tab (layersApi without a baseLayer).
      this.state = { frameIndex: 0, frames: 0, stalls: 0, depthRequests: 0, cameraUploads: 0, uploadMs: 0, callbackMs: 0, sessions: 0, held: false,
        cameraFrames: 0, depthFrames: 0, poseLost: 0, crashes: 0, refusals: [] };
      this.afterFrame = []; // one-shot callbacks right after the next frame's callbacks
      this.heldMs = 0;
      this.heldSince = null;
      this.missingSets = { depth: new Set(config.missingDepth), camera: new Set(config.missingCamera), pose: new Set(config.poseLost ?? []) };
      this.shownIndex = null; // the recording frame of the last XR frame
      this.hasMoved = false;
    }

    missing(what, index) {
      return this.missingSets[what].has(index);
    }

    /** Whether the phone has moved depthAfterMoveM from its first pose by recording frame
     * `index` (once it has, depth from motion keeps coming). */
    moved(index) {
      if (!this.hasMoved) {
        const [a, b] = [config.poses[0], config.poses[index]];
        this.hasMoved = Math.hypot(b[12] - a[12], b[13] - a[13], b[14] - a[14]) >= config.depthAfterMoveM;
      }
      return this.hasMoved;
    }

    start(session) {
      this.session = session;
      this.state.sessions += 1;
      this.t0 = null;
      const tick = () => {
        if (this.session !== session) return;
        this.timer = setTimeout(tick, 1000 / config.displayHz);
        const time = performance.now();
        // Real time from the camera's first frame, less the time the phone was held still
        // (hold()); held at the last frame when the recording ends.
        this.t0 ??= this.recording.frames.has(0) ? time : null;
        const played = this.t0 === null ? 0 : time - this.t0 - this.heldMs - (this.heldSince === null ? 0 : time - this.heldSince);
        const due = Math.min(config.frames - 1, Math.floor((played / 1000) * config.fps));
        this.state.held = due === config.frames - 1;
        this.recording.prefetch(due, this.state.frameIndex);
        const index = this.recording.latest(due);
        if (index === null) return; // the camera has not started: no frame yet
        if (index < due) this.state.stalls += 1;
        // A new camera image in this XR frame, and with every depthEvery-th one a new depth image.
        // Held still, the phone's camera goes on giving (the same) images, and ARCore depth.
        const newCamera = index !== this.shownIndex || this.heldSince !== null || this.state.held;
        this.shownIndex = index;
        if (newCamera) this.state.cameraFrames += 1;
        if (this.missing("pose", index)) this.state.poseLost += 1;
        this.state.frameIndex = index;
        this.state.frames += 1;
        this.log.push([time, index]);
        session._frame(time, index, newCamera && config.depthEvery > 0 && this.state.cameraFrames % config.depthEvery === 0);
        for (const callback of this.afterFrame.splice(0)) callback(index);
        this.state.callbackMs += performance.now() - time;
      };
      this.timer = setTimeout(tick, 1000 / config.displayHz);
    }

    /** Hold the phone still (true) at the frame it shows, or let the recording go on (false)
     * from where it was held. */
    hold(on) {
      const now = performance.now();
      if (on && this.heldSince === null) this.heldSince = now;
      if (!on && this.heldSince !== null) {
        this.heldMs += now - this.heldSince;
        this.heldSince = null;
      }
    }

    sessionEnded(session) {
      if (this.session === session) this.session = null;
      clearTimeout(this.timer);
    }

    /** The camera image of recording frame `index` in `texture` (the camera's size, not the
     * view's), uploaded when the frame changed. GL state is saved and restored: the page's
     * renderer caches it. */
    cameraTexture(gl, index) {
      const [w, h] = config.cameraSize;
      if (this.gl !== gl) {
        this.gl = gl;
        this.texture = gl.createTexture();
        this.source = gl.createTexture();
        this.readFb = gl.createFramebuffer();
        this.drawFb = gl.createFramebuffer();
        this.shown = -1;
        const saved = gl.getParameter(gl.TEXTURE_BINDING_2D);
        gl.bindTexture(gl.TEXTURE_2D, this.texture);
        gl.texStorage2D(gl.TEXTURE_2D, 1, gl.RGBA8, w, h);
        gl.bindTexture(gl.TEXTURE_2D, saved);
      }
      if (this.shown === index) return this.texture;
      const bitmap = this.recording.frames.get(index);
      if (!bitmap) return this.texture;
      const started = performance.now();
      const saved = {
        texture: gl.getParameter(gl.TEXTURE_BINDING_2D),
        read: gl.getParameter(gl.READ_FRAMEBUFFER_BINDING),
        draw: gl.getParameter(gl.DRAW_FRAMEBUFFER_BINDING),
        flip: gl.getParameter(gl.UNPACK_FLIP_Y_WEBGL),
        premultiply: gl.getParameter(gl.UNPACK_PREMULTIPLY_ALPHA_WEBGL),
        alignment: gl.getParameter(gl.UNPACK_ALIGNMENT),
        unpackBuffer: gl.getParameter(gl.PIXEL_UNPACK_BUFFER_BINDING),
        scissor: gl.isEnabled(gl.SCISSOR_TEST),
        rasterizerDiscard: gl.isEnabled(gl.RASTERIZER_DISCARD),
      };
      gl.bindBuffer(gl.PIXEL_UNPACK_BUFFER, null);
      gl.pixelStorei(gl.UNPACK_FLIP_Y_WEBGL, false); // the bitmap is decoded bottom row first
      gl.pixelStorei(gl.UNPACK_PREMULTIPLY_ALPHA_WEBGL, false);
      gl.pixelStorei(gl.UNPACK_ALIGNMENT, 4);
      gl.bindTexture(gl.TEXTURE_2D, this.source);
      gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA8, gl.RGBA, gl.UNSIGNED_BYTE, bitmap);
      gl.disable(gl.SCISSOR_TEST);
      gl.disable(gl.RASTERIZER_DISCARD);
      gl.bindFramebuffer(gl.READ_FRAMEBUFFER, this.readFb);
      gl.framebufferTexture2D(gl.READ_FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, this.source, 0);
      gl.bindFramebuffer(gl.DRAW_FRAMEBUFFER, this.drawFb);
      gl.framebufferTexture2D(gl.DRAW_FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, this.texture, 0);
      gl.blitFramebuffer(0, 0, bitmap.width, bitmap.height, 0, 0, w, h, gl.COLOR_BUFFER_BIT, gl.LINEAR);
      gl.bindFramebuffer(gl.READ_FRAMEBUFFER, saved.read);
      gl.bindFramebuffer(gl.DRAW_FRAMEBUFFER, saved.draw);
      gl.bindTexture(gl.TEXTURE_2D, saved.texture);
      gl.pixelStorei(gl.UNPACK_FLIP_Y_WEBGL, saved.flip);
      gl.pixelStorei(gl.UNPACK_PREMULTIPLY_ALPHA_WEBGL, saved.premultiply);
      gl.pixelStorei(gl.UNPACK_ALIGNMENT, saved.alignment);
      gl.bindBuffer(gl.PIXEL_UNPACK_BUFFER, saved.unpackBuffer);
      if (saved.scissor) gl.enable(gl.SCISSOR_TEST);
      if (saved.rasterizerDiscard) gl.enable(gl.RASTERIZER_DISCARD);
      this.shown = index;
      this.state.cameraUploads += 1;
      this.state.uploadMs += performance.now() - started;
      return this.texture;
    }

    /** What the page drew into the XR layer last, as a PNG data URL (top row first), and the
     * recording frame on screen: the tests' view of the phone's screen without the camera. */
    async readLayer() {
      const layer = this.session?.renderState.baseLayer;
      if (!layer) return null;
      const gl = layer._gl;
      const [w, h] = [layer.framebufferWidth, layer.framebufferHeight];
      const pixels = new Uint8Array(w * h * 4);
      const saved = gl.getParameter(gl.READ_FRAMEBUFFER_BINDING);
      gl.bindFramebuffer(gl.READ_FRAMEBUFFER, layer.framebuffer);
      gl.readPixels(0, 0, w, h, gl.RGBA, gl.UNSIGNED_BYTE, pixels);
      gl.bindFramebuffer(gl.READ_FRAMEBUFFER, saved);
      const flipped = new Uint8ClampedArray(pixels.length);
      const row = w * 4;
      for (let y = 0; y < h; y++) flipped.set(pixels.subarray((h - 1 - y) * row, (h - y) * row), y * row);
      const canvas = new OffscreenCanvas(w, h);
      canvas.getContext("2d").putImageData(new ImageData(flipped, w, h), 0, 0);
      const blob = await canvas.convertToBlob({ type: "image/png" });
      const bytes = new Uint8Array(await blob.arrayBuffer());
      let binary = "";
      for (let i = 0; i < bytes.length; i += 0x8000) binary += String.fromCharCode(...bytes.subarray(i, i + 0x8000));
      return { png: btoa(binary), frameIndex: this.state.frameIndex, size: [w, h] };
    }
  }

  const device = new Device();

  class EmulatedWebGLLayer {
    constructor(session, gl, init = {}) {
      if (!(session instanceof EmulatedSession) || session._ended) throw domError("InvalidStateError", "no active XR session");
      const scale = init.framebufferScaleFactor ?? 1.0;
      this._gl = gl;
      this.antialias = false;
      this.ignoreDepthValues = true;
      this.fixedFoveation = null;
      this.framebufferWidth = Math.round(config.viewSize[0] * scale);
      this.framebufferHeight = Math.round(config.viewSize[1] * scale);
      const saved = { fb: gl.getParameter(gl.FRAMEBUFFER_BINDING), rb: gl.getParameter(gl.RENDERBUFFER_BINDING) };
      this.framebuffer = gl.createFramebuffer();
      gl.bindFramebuffer(gl.FRAMEBUFFER, this.framebuffer);
      for (const [format, attachment] of [[gl.RGBA8, gl.COLOR_ATTACHMENT0], [gl.DEPTH24_STENCIL8, gl.DEPTH_STENCIL_ATTACHMENT]]) {
        const rb = gl.createRenderbuffer();
        gl.bindRenderbuffer(gl.RENDERBUFFER, rb);
        gl.renderbufferStorage(gl.RENDERBUFFER, format, this.framebufferWidth, this.framebufferHeight);
        gl.framebufferRenderbuffer(gl.FRAMEBUFFER, attachment, gl.RENDERBUFFER, rb);
      }
      gl.bindFramebuffer(gl.FRAMEBUFFER, saved.fb);
      gl.bindRenderbuffer(gl.RENDERBUFFER, saved.rb);
    }

    getViewport() {
      return { x: 0, y: 0, width: this.framebufferWidth, height: this.framebufferHeight };
    }

    static getNativeFramebufferScaleFactor() {
      return 1.0;
    }
  }

  class EmulatedWebGLBinding {
    constructor(session, gl) {
      if (!(session instanceof EmulatedSession) || session._ended) throw domError("InvalidStateError", "no active XR session");
      this.session = session;
      this.gl = gl;
    }

    getCameraImage(camera) {
      if (!this.session.enabledFeatures.includes("camera-access")) throw domError("NotSupportedError", "camera-access is not enabled");
      if (config.layersApi && !this.session.renderState.baseLayer) {
        // Chrome 147+ on several phones: the tab crashes ("Aw, Snap!"), three.js issue #33404.
        device.state.crashes += 1;
        throw domError("OperationError", "emulated crash: getCameraImage without an XRWebGLLayer as baseLayer (Chrome 147+ on ARCore)");
      }
      return device.cameraTexture(this.gl, camera._index);
    }

    getDepthInformation() {
      throw domError("InvalidStateError", "this session's depth usage is cpu-optimized");
    }
  }

  /** The WebXR Layers API's part that three.js uses (createProjectionLayer, getViewSubImage),
   * on the layersApi profile only: a projection layer whose textures are plain GL textures of
   * the view's size. Never composited: the tests read what the page drew from the baseLayer. */
  class EmulatedLayersBinding extends EmulatedWebGLBinding {
    createProjectionLayer(init = {}) {
      const gl = this.gl;
      const [w, h] = config.viewSize.map((v) => Math.round(v * (init.scaleFactor ?? 1)));
      const texture = (format) => {
        const saved = gl.getParameter(gl.TEXTURE_BINDING_2D);
        const t = gl.createTexture();
        gl.bindTexture(gl.TEXTURE_2D, t);
        gl.texStorage2D(gl.TEXTURE_2D, 1, format, w, h);
        gl.bindTexture(gl.TEXTURE_2D, saved);
        return t;
      };
      return { textureWidth: w, textureHeight: h, ignoreDepthValues: true, fixedFoveation: null, _colour: texture(gl.RGBA8),
        _depth: init.depthFormat ? texture(init.depthFormat) : null };
    }

    getViewSubImage(layer) {
      return { colorTexture: layer._colour, depthStencilTexture: layer._depth,
        viewport: { x: 0, y: 0, width: layer.textureWidth, height: layer.textureHeight } };
    }
  }

  const xr = new EventTarget();
  xr.isSessionSupported = async (mode) => mode === "immersive-ar" || mode === "inline";
  xr.requestSession = async (mode, options = {}) => {
    // An immersive session only from a user's gesture (WebXR: "triggered by user activation",
    // else SecurityError; Chrome: "The requested session requires user activation.").
    if (!navigator.userActivation.isActive) {
      device.state.refusals.push("no user activation");
      throw domError("SecurityError", "The requested session requires user activation.");
    }
    if (mode !== "immersive-ar") throw domError("NotSupportedError", `${mode} sessions are not supported by this device`);
    if (device.session) throw domError("InvalidStateError", "an immersive session is already active");
    // The user refused the camera permission (or Chrome's prompt for it): camera-access is not
    // granted; a session that requires it is refused as any unsupported required feature.
    const granted = config.cameraDenied ? config.features.filter((f) => f !== "camera-access") : config.features;
    const supported = new Set(["viewer", "local", "local-floor", "dom-overlay", "hit-test", "anchors", ...granted]);
    const required = options.requiredFeatures ?? [];
    const missing = required.filter((f) => !supported.has(f));
    if (missing.length) {
      device.state.refusals.push(`required: ${missing.join(", ")}`);
      throw domError("NotSupportedError", "The specified session configuration is not supported.");
    }
    const features = new Set(["viewer", "local"]);
    for (const f of [...required, ...(options.optionalFeatures ?? [])]) if (supported.has(f)) features.add(f);
    let depthUsage, depthFormat;
    if (features.has("depth-sensing")) {
      const prefs = options.depthSensing;
      if (!prefs) throw new TypeError("depth-sensing needs the depthSensing usage and data format preferences");
      depthUsage = (prefs.usagePreference ?? []).find((u) => u === "cpu-optimized");
      depthFormat = (prefs.dataFormatPreference ?? []).find((f) => config.depthFormats.includes(f));
      if (!depthUsage || !depthFormat) {
        if (required.includes("depth-sensing")) throw domError("NotSupportedError", "no supported depth usage or data format among the preferences");
        features.delete("depth-sensing");
      }
    }
    await device.recording.load(); // ARCore takes a moment to start, too
    const session = new EmulatedSession(device, features, depthUsage, depthFormat, options.domOverlay?.root);
    device.start(session);
    return session;
  };

  Object.defineProperty(Navigator.prototype, "xr", { get: () => xr, configurable: true });
  if (config.cameraDenied) {
    // What the page can learn of the refusal: the camera permission's state.
    const query = Permissions.prototype.query;
    Permissions.prototype.query = function (descriptor) {
      if (descriptor?.name === "camera") return Promise.resolve({ name: "camera", state: "denied", onchange: null });
      return query.call(this, descriptor);
    };
  }
  window.XRWebGLLayer = EmulatedWebGLLayer;
  window.XRWebGLBinding = config.layersApi ? EmulatedLayersBinding : EmulatedWebGLBinding;
  window.XRRigidTransform = EmulatedRigidTransform;
  for (const proto of [WebGLRenderingContext.prototype, WebGL2RenderingContext.prototype]) {
    proto.makeXRCompatible = async function () {};
  }
  window.__xrDevice = { state: device.state, log: device.log, readLayer: () => device.readLayer(), hold: (on) => device.hold(on),
    active: () => device.session !== null,
    afterNextFrame: (callback) => device.afterFrame.push(callback), recording: device.recording };
})();
