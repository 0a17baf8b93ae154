// Live source: the phone's camera and depth through WebXR (Chrome on Android with ARCore).
// An immersive-ar session with depth-sensing (cpu-optimized) and camera-access; each captured
// frame is the camera image read back from its WebGL texture (downscaled, JPEG), the depth
// buffer resampled onto the view and packed as zlib uint16 millimetres, and the view's pose in
// the XR space, which anchors the AR overlay of that frame. Intrinsics come from the view's
// projection matrix and viewport; gravity from the gravity-aligned "local" reference space.

import * as THREE from "three";
import {
  DEPTH_SCALE_MM, depthSizeFor, deviceCameraFromView, encodeJpeg, flipRows, gravityInCamera, intrinsicsFromProjection,
  packDepth, resampleDepth, scaleIntrinsics,
} from "../packing.js";

const COLOUR_LONG_SIDE = 640; // colour sent at 640 px on the long side (see PROTOCOL.md, bandwidth)
const ANCHORS_KEPT = 64;
const READ_POLL_MS = 2; // how often a camera read looks whether the GPU has written its pixels

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
   * @param {import("../ar_view.js").ARView} arView its renderer draws the XR overlay
   * @param {HTMLElement} overlayRoot shown over the camera (dom-overlay): HUD and controls
   */
  constructor(arView, overlayRoot) {
    this.kind = "live";
    this.arView = arView;
    this.overlayRoot = overlayRoot;
    this.anchors = new Map(); // seq -> Matrix4 (XR pose of the frame's GL camera)
    this.request = null; // {resolve, reject} of the next capture
    this.onEnd = null;
  }

  /** Start the XR session; resolves with the camera description for the hello. */
  async start() {
    const options = {
      requiredFeatures: ["depth-sensing", "camera-access", "local"],
      optionalFeatures: ["dom-overlay"],
      depthSensing: { usagePreference: ["cpu-optimized"], dataFormatPreference: ["luminance-alpha", "float32"] },
      domOverlay: { root: this.overlayRoot },
    };
    try {
      this.session = await navigator.xr.requestSession("immersive-ar", options);
    } catch (exc) {
      throw new Error(`AR could not start with depth sensing and camera access (${exc.name}: ${exc.message}). ` +
        "This device or browser gives the web no depth or no camera image; use replay instead.");
    }
    const renderer = this.arView.renderer;
    renderer.xr.enabled = true;
    renderer.xr.setReferenceSpaceType("local");
    await renderer.xr.setSession(this.session);
    this.gl = renderer.getContext();
    this.binding = new XRWebGLBinding(this.session, this.gl);
    this.space = renderer.xr.getReferenceSpace();
    this.session.addEventListener("end", () => this.#ended());
    // Taps on the page (sticks, buttons, the AR view) are the page's, not XR select input.
    this.overlayRoot.addEventListener("beforexrselect", (e) => e.preventDefault());
    this.arView.xrAnchor = (seq) => this.anchors.get(seq) ?? null;
    this.arView.container.classList.add("xr");
    this.info = await new Promise((resolve, reject) => {
      this.describe = { resolve, reject };
      renderer.setAnimationLoop((time, frame) => this.#onFrame(time, frame));
    });
    return this.info;
  }

  #ended() {
    this.arView.renderer.setAnimationLoop(null);
    this.arView.renderer.xr.enabled = false;
    this.arView.xrAnchor = null;
    this.arView.container.classList.remove("xr");
    this.request?.reject(new Error("AR session ended"));
    this.request = null;
    this.session = null;
    this.onEnd?.();
  }

  stop() {
    this.session?.end();
  }

  /** The next XR frame, read: resolves {packing, anchor} once its pixels are copied out of the
   * XR frame (packing: a promise of {fields, bitmap}, settled while the next frame may be read),
   * or {skip: reason} when this frame has no depth or no camera image. */
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
    // three's loop also runs on the window's animation frames (no XR frame): nothing to do then.
    if (!frame) return;
    const pose = frame.getViewerPose(this.space);
    if (pose) this.#occlusionDepth(frame, pose.views[0]);
    this.arView.render(1 / 60);
    if (!pose) return;
    const view = pose.views[0];
    const layer = this.session.renderState.baseLayer;
    if (this.describe) {
      const depth = frame.getDepthInformation(view);
      if (!view.camera || !depth) return; // not ready yet
      const viewport = layer.getViewport(view);
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
    const request = this.request;
    this.request = null;
    try {
      const depth = frame.getDepthInformation(view);
      // Normal while ARCore (re)initialises: this frame has no depth or no camera image. It is
      // skipped and counted, and capture goes on with the next one.
      if (!depth || !view.camera) {
        request.resolve({ skip: !depth ? "no depth" : "no camera image" });
        return;
      }
      // Both copied out now: the camera texture and the depth buffer are only valid in this frame.
      const reading = this.#readCamera(view);
      const depthValues = this.#depthValues(depth);
      const anchor = new THREE.Matrix4().fromArray(view.transform.matrix);
      // Stamped with the XR frame's time (when its camera image was taken), not the request's;
      // the phone's own pose of this image goes along as the tracker's prior.
      const deviceCamera = deviceCameraFromView(view.transform.matrix);
      const packing = reading.then((rgba) => this.#pack(rgba, depthValues, depth.rawValueToMeters))
        .then((packed) => ({ ...packed, fields: { ...packed.fields, timestamp: time / 1000, deviceCamera } }));
      request.resolve({ packing, anchor });
    } catch (exc) {
      request.reject(exc);
    }
  }

  /** The current XR frame's depth, in metres, for occlusion in the overlay drawn over this very
   * view (occlusion.js; the buffer is only readable inside the frame, so it is copied here). */
  #occlusionDepth(frame, view) {
    const occlusion = this.arView.occlusion;
    if (!occlusion.enabled) return;
    const depth = frame.getDepthInformation(view);
    if (!depth) {
      occlusion.clearDepth();
      return;
    }
    const raw = this.session.depthDataFormat === "float32" ? new Float32Array(depth.data) : new Uint16Array(depth.data);
    const metres = new Float32Array(raw.length);
    for (let i = 0; i < raw.length; i++) metres[i] = raw[i] * depth.rawValueToMeters;
    occlusion.setDepth(metres, depth.width, depth.height, null, depth.normDepthBufferFromNormView.matrix);
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

  /** The depth buffer resampled onto depthSize (raw values, times rawValueToMeters for metres):
   * "luminance-alpha" and "unsigned-short" are uint16, "float32" float. */
  #depthValues(depthInfo) {
    const [dw, dh] = this.depthSize;
    const raw = this.session.depthDataFormat === "float32" ? new Float32Array(depthInfo.data) : new Uint16Array(depthInfo.data);
    return resampleDepth(raw, depthInfo.width, depthInfo.height, dw, dh, depthInfo.normDepthBufferFromNormView.matrix);
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
