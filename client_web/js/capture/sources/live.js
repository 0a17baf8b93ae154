// Live source: the phone's camera and depth through WebXR (Chrome on Android with ARCore).
// An immersive-ar session with depth-sensing (cpu-optimized) and camera-access; each captured
// frame is the camera image read back from its WebGL texture (downscaled, JPEG), the depth
// buffer resampled onto the view and packed as zlib uint16 millimetres, and the view's pose in
// the XR space, which anchors the AR overlay of that frame. Intrinsics come from the view's
// projection matrix and viewport; gravity from the gravity-aligned "local" reference space.
//
// The page owns the XR session's rendering: its own XRWebGLLayer as the session's baseLayer,
// its own XRWebGLBinding, its own XR animation loop, and three.js drawing into that layer's
// framebuffer. three's WebXRManager (renderer.xr) is not used: since Chrome 147 it takes the
// WebXR Layers path whenever XRWebGLBinding.prototype.createProjectionLayer exists, leaving
// renderState.baseLayer null, and getCameraImage on such a session crashes the tab on several
// phones (three.js issue #33404); a page with its own XRWebGLLayer does not crash, on Chrome 146
// and 147+ alike.
//
// Chrome's depth: getDepthInformation gives depth only on XR frames with a new ARCore depth
// image (it comes slower than the camera) and none at all until the phone has moved. The
// latest depth is kept, copied out of its frame, and a captured camera image goes with it if it
// came at most DEPTH_MAX_AGE_MS before and has not gone out with another (else the capture waits
// for the next depth image); occlusion uses it for as long. While there is none the user is told
// on screen to move the phone; if none comes at all, AR stops and says why.
//
// Tracking loss: while ARCore is not tracking, XR frames have no viewer pose (nothing is drawn
// or captured); when it tracks again, its local space may have jumped (it relocalised). The
// phone's pose is sent as the tracker's prior (T_device_camera, "in the device's world"), so
// after each loss the page counts a new device world and sends its number with each frame
// (device_world): the server's tracker then does not take the step across as the camera's
// motion, and finds again where the device's world lies in the map.

import * as THREE from "three";
import {
  DEPTH_SCALE_MM, depthSizeFor, deviceCameraFromView, encodeJpeg, flipRows, gravityInCamera, intrinsicsFromProjection,
  packDepth, resampleDepth, scaleIntrinsics,
} from "../packing.js";
import { LIVE_DEPTH_SENSING } from "../live_needs.js";

const COLOUR_LONG_SIDE = 640; // colour sent at 640 px on the long side (see PROTOCOL.md, bandwidth)
const ANCHORS_KEPT = 64;
const READ_POLL_MS = 2; // how often a camera read looks whether the GPU has written its pixels
// A camera image is sent with the latest depth if that came at most this long before it, and
// occlusion keeps using it as long. ARCore's depth comes at 10-15 Hz beside a 30 Hz camera (a new
// depth image every 67-100 ms): 150 ms covers one late depth image; older depth would be paired
// with a view that has moved on (at a brisk 30 degrees/s, 4.5 degrees: ~30 px at 640 px).
export const DEPTH_MAX_AGE_MS = 150;
// No depth for this long (none yet, or none within DEPTH_MAX_AGE_MS): the user is told to move
// the phone (depth from motion needs it); not sooner, so that a late depth image or two do not
// make the hint flicker.
const DEPTH_HINT_AFTER_MS = 500;
// No depth at all this long after the session's first XR frame: AR stops with a message saying
// why (ARCore's depth comes within a second or two of moving the phone where it can measure).
export const FIRST_DEPTH_TIMEOUT_MS = 10000;
export const HINTS = Object.freeze({
  moveForDepth: "Move the phone slowly sideways: AR measures depth from the camera's motion, and has none yet.",
  trackingLost: "AR lost tracking: hold the phone steady and point it at a lit, textured place it has seen.",
  noDepth: `No depth from this phone in ${FIRST_DEPTH_TIMEOUT_MS / 1000} s of AR, so live AR stopped. ` +
    "Start again and move the phone slowly sideways over a lit, textured scene; if depth still never comes, this " +
    "phone's ARCore gives the web no depth: use replay instead.",
});

const CHECK_PAGE = "Open /check on this phone to see what its browser offers.";

/** What to tell the user when requestSession is refused, by the DOMException's name (WebXR:
 * SecurityError without a user's tap, NotSupportedError for a mode or feature the device
 * lacks, NotAllowedError when the user or a policy declined). */
export function refusalMessage(exc) {
  const why = `(${exc?.name}: ${exc?.message})`;
  switch (exc?.name) {
    case "SecurityError":
      return `AR starts only from a tap on the page: tap Start. ${why}`;
    case "NotAllowedError":
      return `AR was not allowed on this page: accept Chrome's AR and camera prompts when you tap Start, or allow them ` +
        `in the site's settings (the lock icon by the address). ${why}`;
    case "InvalidStateError":
      return `Another AR session is still open: close it (or reload this page) and tap Start again. ${why}`;
    default:
      return `This phone or browser could not start AR: it needs Chrome on Android with Google Play Services for AR ` +
        `installed and up to date. ${CHECK_PAGE} ${why}`;
  }
}

/** Why a started session cannot stream (no depth, no camera image), or null when it can. A
 * browser without enabledFeatures (before Chrome 116) is taken at its word here; its missing
 * depth or camera image are then found in its frames. */
export async function missingFeatureMessage(session) {
  const enabled = session.enabledFeatures;
  if (!enabled) return null;
  if (!enabled.includes("camera-access")) {
    let permission = null;
    try {
      permission = (await navigator.permissions.query({ name: "camera" })).state;
    } catch {
      permission = null; // a browser that cannot say
    }
    if (permission === "denied") {
      return "Live AR needs the camera image, and the camera permission was refused for this site: allow the camera " +
        "(Chrome: the lock icon by the address, Permissions, Camera), then tap Start again.";
    }
    return `This browser gives AR pages no camera image (WebXR camera access: Chrome 107+ on Android). Update Chrome, ` +
      `or use replay instead. ${CHECK_PAGE}`;
  }
  if (!enabled.includes("depth-sensing")) {
    return `This phone gives AR pages no depth (ARCore's Depth API is not supported on this device, or this browser ` +
      `has no WebXR depth sensing): live AR needs it. Use replay instead. ${CHECK_PAGE}`;
  }
  return null;
}

/** Whether this browser can run the live mode, and if not, why, in plain words. */
export async function liveSupport() {
  if (!window.isSecureContext) {
    return { supported: false, reason: "Live AR needs a secure page: start the server with --tls and open its https:// address on the phone." };
  }
  if (!navigator.xr) {
    return { supported: false, reason: "This browser has no WebXR. Live AR needs Chrome on an Android phone with ARCore (Google Play Services for AR)." };
  }
  let ar = false;
  try {
    ar = await navigator.xr.isSessionSupported("immersive-ar");
  } catch {
    ar = false;
  }
  if (!ar) {
    return { supported: false, reason: "This browser or device does not offer WebXR immersive-ar (AR). Live AR needs Chrome on an Android phone with ARCore." };
  }
  return { supported: true, reason: "WebXR immersive-ar is available; depth sensing and camera access are checked when AR starts." };
}

export class LiveSource {
  /**
   * @param {import("../../views/ar_view.js").ARView} arView its renderer draws the XR overlay
   * @param {HTMLElement} overlayRoot shown over the camera (dom-overlay): HUD and controls
   */
  constructor(arView, overlayRoot) {
    this.kind = "live";
    this.arView = arView;
    this.overlayRoot = overlayRoot;
    this.anchors = new Map(); // seq -> Matrix4 (XR pose of the frame's GL camera)
    this.request = null; // {resolve, reject} of the next capture
    this.onEnd = null;
    this.depth = null; // the latest depth, copied out of its frame (#keepDepth)
    this.occlusionDepth = null; // the depth the overlay's occlusion was last given
    this.poseLost = false; // ARCore gives no viewer pose (not tracking)
    this.trackedSince = null; // XR time since which it has (again)
    this.firstFrameAt = null; // XR time of the session's first frame (FIRST_DEPTH_TIMEOUT_MS)
    this.lastDrawn = undefined; // XR time the overlay was last drawn
    this.worlds = 0; // tracking losses so far: the device world's number (frames' device_world)
    this.stats = { depthImages: 0, pairedOlder: 0, maxPairedAgeMs: 0, poseLostFrames: 0 };
    this.said = []; // [XR time ms, text] of each line shown to the user (#say), the latest 50
    this.hint = arView.xrHint;
    this.#say(null);
  }

  /** Start the XR session (call it from the user's tap: a browser starts AR only from one);
   * resolves with the camera description for the hello. Rejects with a message that says what
   * to do when AR cannot start, or when the session lacks depth or the camera image. */
  async start() {
    // Depth and the camera image are asked for, not required: a browser refuses a required
    // feature it lacks with the same error as anything else it cannot do, while a session
    // without it tells which one is missing (enabledFeatures), so the user can be told.
    const options = {
      requiredFeatures: ["local"],
      optionalFeatures: ["depth-sensing", "camera-access", "dom-overlay"],
      depthSensing: { usagePreference: [...LIVE_DEPTH_SENSING.usagePreference],
        dataFormatPreference: [...LIVE_DEPTH_SENSING.dataFormatPreference] },
      domOverlay: { root: this.overlayRoot },
    };
    try {
      this.session = await navigator.xr.requestSession("immersive-ar", options);
    } catch (exc) {
      throw new Error(refusalMessage(exc));
    }
    const session = this.session;
    const missing = await missingFeatureMessage(session);
    if (missing) {
      this.session = null;
      await session.end().catch(() => {});
      throw new Error(missing);
    }
    const renderer = this.arView.renderer;
    const gl = renderer.getContext();
    this.gl = gl;
    if (gl.getContextAttributes().xrCompatible !== true) await gl.makeXRCompatible();
    // The page's own layer (see the top of this file: not three's WebXRManager, whose layers path
    // leaves baseLayer null on Chrome 147+, where getCameraImage then crashes).
    const attributes = gl.getContextAttributes();
    this.layer = new XRWebGLLayer(session, gl, { antialias: attributes.antialias, alpha: true, depth: true,
      stencil: attributes.stencil, framebufferScaleFactor: 1.0 });
    session.updateRenderState({ baseLayer: this.layer });
    this.binding = new XRWebGLBinding(session, gl);
    this.space = await session.requestReferenceSpace("local");
    // three draws into the layer's framebuffer through a render target bound to it (what
    // WebXRManager does for an XRWebGLLayer); isXRRenderTarget: its pixels are the screen's, so
    // three converts colours to the output colour space as for the canvas.
    this.target = new THREE.WebGLRenderTarget(this.layer.framebufferWidth, this.layer.framebufferHeight, {
      format: THREE.RGBAFormat, type: THREE.UnsignedByteType, colorSpace: renderer.outputColorSpace,
      stencilBuffer: attributes.stencil,
    });
    this.target.isXRRenderTarget = true;
    renderer.setRenderTargetFramebuffer(this.target, this.layer.framebuffer);
    this.xrCamera = new THREE.PerspectiveCamera();
    this.xrCamera.matrixAutoUpdate = false;
    session.addEventListener("end", () => this.#ended());
    // Taps on the page (sticks, buttons, the AR view) are the page's, not XR select input.
    this.overlayRoot.addEventListener("beforexrselect", (e) => e.preventDefault());
    this.arView.xrAnchor = (seq) => this.anchors.get(seq) ?? null;
    this.arView.container.classList.add("xr");
    this.info = await new Promise((resolve, reject) => {
      this.describe = { resolve, reject };
      session.requestAnimationFrame(this.#loop);
    });
    return this.info;
  }

  #loop = (time, frame) => {
    if (!this.session || frame.session !== this.session) return;
    this.session.requestAnimationFrame(this.#loop); // first: a failing frame must not stop the loop
    this.#onFrame(time, frame);
  };

  #ended() {
    const renderer = this.arView.renderer;
    if (renderer.getRenderTarget() === this.target) renderer.setRenderTarget(null);
    // Dropped, not disposed: its framebuffer is the XR layer's (setRenderTargetFramebuffer),
    // which three would delete, an invalid operation on a layer's framebuffer (three's own
    // WebXRManager drops its target the same way).
    this.target = null;
    this.arView.xrAnchor = null;
    this.arView.container.classList.remove("xr");
    if (this.hint.textContent !== HINTS.noDepth) this.#say(null); // that one says why AR stopped
    this.request?.reject(new Error("AR session ended"));
    this.request = null;
    this.describe?.reject(new Error("AR ended before it gave a camera image with depth"));
    this.describe = null;
    this.session = null;
    this.onEnd?.();
  }

  stop() {
    this.session?.end();
  }

  /** The next XR frame, read: resolves {packing, anchor} once its pixels are copied out of the
   * XR frame (packing: a promise of {fields, bitmap}, settled while the next frame may be read),
   * or {skip: reason} when this frame has no pose, no recent depth or no camera image. */
  capture(tick, timestamp) {
    if (!this.session) return Promise.resolve(null);
    return new Promise((resolve, reject) => (this.request = { resolve, reject }));
  }

  /** Remember the anchor of a sent frame under its seq (the overlay of that frame uses it). */
  keep(seq, anchor) {
    this.anchors.set(seq, anchor);
    for (const key of this.anchors.keys()) if (this.anchors.size > ANCHORS_KEPT) this.anchors.delete(key);
  }

  #onFrame(time, frame) {
    this.firstFrameAt ??= time;
    this.trackedSince ??= time;
    const pose = frame.getViewerPose(this.space);
    if (!pose) {
      this.#trackingLost(time);
      return;
    }
    if (this.poseLost) {
      // Tracking again, perhaps relocalised: a new device world for the prior (top of the file).
      this.poseLost = false;
      this.trackedSince = time;
      this.worlds += 1;
    }
    const view = pose.views[0];
    const fresh = frame.getDepthInformation(view);
    if (fresh) this.#keepDepth(fresh, time);
    const depth = this.depth && time - this.depth.time <= DEPTH_MAX_AGE_MS ? this.depth : null;
    this.#occlusionDepth(depth);
    this.#draw(time, view);
    // Depth missing since the last depth image, or since ARCore tracks (again): depth does not
    // come while it is not tracking, so that time is not held against it.
    const sinceDepth = time - Math.max(this.depth?.time ?? -Infinity, this.trackedSince);
    this.#say(sinceDepth > DEPTH_HINT_AFTER_MS ? HINTS.moveForDepth : null, time);
    if (this.describe) {
      if (!this.depth && time - this.firstFrameAt > FIRST_DEPTH_TIMEOUT_MS) {
        this.#say(HINTS.noDepth, time);
        this.describe.reject(new Error(HINTS.noDepth));
        this.describe = null;
        this.session.end();
        return;
      }
      if (!view.camera || !depth) return; // not ready yet
      const viewport = this.layer.getViewport(view);
      const scale = COLOUR_LONG_SIDE / Math.max(view.camera.width, view.camera.height);
      const colourSize = [Math.round(view.camera.width * scale), Math.round(view.camera.height * scale)];
      const K = intrinsicsFromProjection(view.projectionMatrix, viewport.width, viewport.height);
      this.colourSize = colourSize;
      this.depthSize = depthSizeFor(colourSize, depth.width, depth.height);
      this.describe.resolve({
        clientName: `web/1.0 live (${navigator.userAgent.match(/\(([^)]*)\)/)?.[1] ?? "XR"})`.slice(0, 64),
        intrinsics: scaleIntrinsics(K, [viewport.width, viewport.height], colourSize),
        colourSize, depthSize: this.depthSize, depthScale: DEPTH_SCALE_MM,
        gravity: gravityInCamera(view.transform.matrix),
      });
      this.describe = null;
    }
    if (!this.request) return;
    // Each depth image goes out once: a frame sent with a depth image already sent would be
    // held by the server's tracker as a repeat (not tracked, not fused), for the price of a
    // frame. While depth flows (the latest within DEPTH_MAX_AGE_MS) and that one was sent, the
    // capture waits for the next depth image.
    if (depth && depth.sent) return;
    const request = this.request;
    this.request = null;
    try {
      // Normal while ARCore (re)initialises or has no new depth image for a while: skipped and
      // counted, and capture goes on with the next frame.
      if (!depth || !view.camera) {
        request.resolve({ skip: !depth ? "no depth" : "no camera image" });
        return;
      }
      depth.sent = true;
      // The camera texture is only valid in this frame: copied out now (the depth already was).
      const reading = this.#readCamera(view);
      const depthValues = this.#depthValues(depth);
      const age = time - depth.time;
      if (age > 0) this.stats.pairedOlder += 1;
      this.stats.maxPairedAgeMs = Math.max(this.stats.maxPairedAgeMs, age);
      const anchor = new THREE.Matrix4().fromArray(view.transform.matrix);
      // Stamped with the XR frame's time (when its camera image was taken), not the request's;
      // the phone's own pose of this image, in the current device world, goes along as the
      // tracker's prior.
      const deviceCamera = deviceCameraFromView(view.transform.matrix);
      const deviceWorld = this.worlds;
      const packing = reading.then((rgba) => this.#pack(rgba, depthValues, depth.rawValueToMeters))
        .then((packed) => ({ ...packed, fields: { ...packed.fields, timestamp: time / 1000, deviceCamera, deviceWorld } }));
      request.resolve({ packing, anchor });
    } catch (exc) {
      request.reject(exc);
    }
  }

  /** No viewer pose in this frame (ARCore is not tracking): nothing to draw over the camera,
   * nothing to capture; the user is told what to do. */
  #trackingLost(time) {
    this.poseLost = true;
    this.stats.poseLostFrames += 1;
    this.#say(HINTS.trackingLost, time);
    const renderer = this.arView.renderer;
    renderer.setRenderTarget(this.target);
    renderer.clear(); // no overlay drawn at a pose ARCore no longer knows
    renderer.setRenderTarget(null);
    this.request?.resolve({ skip: "no pose" });
    this.request = null;
  }

  /** Keep this frame's depth: the buffer is readable only inside its frame, so it is copied. */
  #keepDepth(info, time) {
    const data = info.data.slice(0);
    this.depth = {
      time, width: info.width, height: info.height, rawValueToMeters: info.rawValueToMeters,
      values: this.session.depthDataFormat === "float32" ? new Float32Array(data) : new Uint16Array(data),
      depthFromView: Float32Array.from(info.normDepthBufferFromNormView.matrix),
    };
    this.stats.depthImages += 1;
  }

  /** The depth for occlusion in the overlay drawn over this view, in metres (occlusion.js): the
   * latest depth within DEPTH_MAX_AGE_MS, converted once per depth image; none: the mesh, or
   * nothing, hides the drone. */
  #occlusionDepth(depth) {
    const occlusion = this.arView.occlusion;
    if (!occlusion.enabled) return;
    if (!depth) {
      occlusion.clearDepth();
      this.occlusionDepth = null;
      return;
    }
    if (depth === this.occlusionDepth) return;
    const { values, width, height, depthFromView, rawValueToMeters } = depth;
    occlusion.setDepth(values, width, height, null, depthFromView, rawValueToMeters);
    this.occlusionDepth = depth;
  }

  /** Draw the overlay into the XR layer, from this view's pose and projection. */
  #draw(time, view) {
    const renderer = this.arView.renderer;
    const viewport = this.layer.getViewport(view);
    this.target.viewport.set(viewport.x, viewport.y, viewport.width, viewport.height);
    const camera = this.xrCamera;
    camera.matrix.fromArray(view.transform.matrix);
    camera.matrixWorldNeedsUpdate = true;
    camera.projectionMatrix.fromArray(view.projectionMatrix);
    camera.projectionMatrixInverse.copy(camera.projectionMatrix).invert();
    const dt = this.lastDrawn === undefined ? 1 / 60 : Math.min(0.1, (time - this.lastDrawn) / 1000);
    this.lastDrawn = time;
    renderer.setRenderTarget(this.target);
    this.arView.render(dt, camera);
    // The page's window-frame loop may draw the AR view to its canvas before the first pose.
    renderer.setRenderTarget(null);
  }

  /** Show a line to the user over the AR view, or hide it (null). */
  #say(text, time = performance.now()) {
    if (this.hint.textContent === (text ?? "") && this.hint.hidden === !text) return;
    this.hint.textContent = text ?? "";
    this.hint.hidden = !text;
    if (text) this.said.push([time, text]);
    if (this.said.length > 50) this.said.shift();
  }

  /** The camera image, downscaled to colourSize, as top-down RGBA ImageData (a promise). The
   * camera texture is blitted into a small renderbuffer (a full-size read of a 1920 px camera
   * image at 15 fps would cost ~170 MB/s) and read into a pixel buffer without waiting for the
   * GPU: the pixels are taken once its fence signals, while the page goes on (a synchronous
   * readPixels stalls the whole GL pipeline, the overlay's frames with it). If the blit fails,
   * the image is read at full size, synchronously. */
  #readCamera(view) {
    const gl = this.gl;
    const texture = this.binding.getCameraImage(view.camera);
    const [w, h] = this.colourSize;
    const [cw, ch] = [view.camera.width, view.camera.height];
    const previous = gl.getParameter(gl.FRAMEBUFFER_BINDING);
    this.readFb ??= gl.createFramebuffer();
    this.smallFb ??= gl.createFramebuffer();
    if (!this.smallRb) {
      this.smallRb = gl.createRenderbuffer();
      gl.bindRenderbuffer(gl.RENDERBUFFER, this.smallRb);
      gl.renderbufferStorage(gl.RENDERBUFFER, gl.RGBA8, w, h);
      gl.bindFramebuffer(gl.FRAMEBUFFER, this.smallFb);
      gl.framebufferRenderbuffer(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.RENDERBUFFER, this.smallRb);
    }
    gl.getError(); // clear earlier errors: the next check is about the blit
    gl.bindFramebuffer(gl.READ_FRAMEBUFFER, this.readFb);
    gl.framebufferTexture2D(gl.READ_FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, texture, 0);
    gl.bindFramebuffer(gl.DRAW_FRAMEBUFFER, this.smallFb);
    gl.blitFramebuffer(0, 0, cw, ch, 0, 0, w, h, gl.COLOR_BUFFER_BIT, gl.LINEAR);
    let image;
    if (gl.getError() === gl.NO_ERROR) {
      gl.bindFramebuffer(gl.READ_FRAMEBUFFER, this.smallFb);
      image = this.#readAsync(w, h);
    } else {
      const pixels = new Uint8Array(cw * ch * 4);
      gl.readPixels(0, 0, cw, ch, gl.RGBA, gl.UNSIGNED_BYTE, pixels);
      const full = new OffscreenCanvas(cw, ch);
      full.getContext("2d").putImageData(new ImageData(flipRows(pixels, cw, ch), cw, ch), 0, 0);
      const small = new OffscreenCanvas(w, h).getContext("2d");
      small.drawImage(full, 0, 0, w, h);
      image = Promise.resolve(small.getImageData(0, 0, w, h));
    }
    gl.bindFramebuffer(gl.FRAMEBUFFER, previous);
    this.arView.renderer.resetState(); // three.js tracks GL state: tell it we touched it
    return image;
  }

  /** The bound read framebuffer's w x h pixels, read into a pixel-pack buffer now and taken
   * out when the GPU has written them: a promise of top-down ImageData. */
  #readAsync(w, h) {
    const gl = this.gl;
    this.pixelBuffers ??= [];
    let buffer = this.pixelBuffers.pop();
    if (buffer) {
      gl.bindBuffer(gl.PIXEL_PACK_BUFFER, buffer);
    } else {
      // Sized once: the colour size is fixed for the session, and a buffer is reused once read.
      buffer = gl.createBuffer();
      gl.bindBuffer(gl.PIXEL_PACK_BUFFER, buffer);
      gl.bufferData(gl.PIXEL_PACK_BUFFER, w * h * 4, gl.STREAM_READ);
    }
    gl.readPixels(0, 0, w, h, gl.RGBA, gl.UNSIGNED_BYTE, 0);
    gl.bindBuffer(gl.PIXEL_PACK_BUFFER, null);
    const fence = gl.fenceSync(gl.SYNC_GPU_COMMANDS_COMPLETE, 0);
    gl.flush();
    return new Promise((resolve, reject) => {
      const poll = () => {
        if (gl.isContextLost()) {
          reject(new Error("the WebGL context was lost while reading the camera image"));
          return;
        }
        if (gl.clientWaitSync(fence, 0, 0) === gl.TIMEOUT_EXPIRED) {
          setTimeout(poll, READ_POLL_MS);
          return;
        }
        gl.deleteSync(fence);
        const pixels = new Uint8Array(w * h * 4);
        gl.bindBuffer(gl.PIXEL_PACK_BUFFER, buffer);
        gl.getBufferSubData(gl.PIXEL_PACK_BUFFER, 0, pixels);
        gl.bindBuffer(gl.PIXEL_PACK_BUFFER, null);
        this.pixelBuffers.push(buffer);
        resolve(new ImageData(flipRows(pixels, w, h), w, h)); // GL rows are bottom-up
      };
      setTimeout(poll, 0);
    });
  }

  /** A kept depth buffer (#keepDepth) resampled onto depthSize (raw values, times
   * rawValueToMeters for metres): "luminance-alpha" and "unsigned-short" are uint16, "float32"
   * float. */
  #depthValues(depth) {
    const [dw, dh] = this.depthSize;
    return resampleDepth(depth.values, depth.width, depth.height, dw, dh, depth.depthFromView);
  }

  async #pack(rgba, depthValues, rawValueToMeters) {
    const [colour, depth, bitmap] = await Promise.all([
      encodeJpeg(rgba, 0.8),
      packDepth(depthValues, { rawValueToMeters, depthScale: DEPTH_SCALE_MM }),
      createImageBitmap(rgba),
    ]);
    return { bitmap, fields: { colour, ...depth } };
  }
}
