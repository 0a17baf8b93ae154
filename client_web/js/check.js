// The device check page (/check): what this phone's browser offers live AR, step by step, each
// with a pass / fail / unknown (or info) line, as one JSON report a user can download and send
// us. Live AR fails on real phones for reasons the emulated device of the tests cannot show;
// this page measures them where they happen. The AR session itself is capture/check_session.js.

import { MAX_MS, MEASURE_MS, SessionProbe, sessionOptions } from "./capture/check_session.js";
import { LIVE_DEPTH_SENSING } from "./capture/live_needs.js";

const $ = (selector) => document.querySelector(selector);
// What live AR asks of a session (LiveSource.start): depth sensing, cpu-optimized, in one of
// these formats, and camera access.
const [LIVE_DEPTH_USAGE] = LIVE_DEPTH_SENSING.usagePreference;
const LIVE_DEPTH_FORMATS = LIVE_DEPTH_SENSING.dataFormatPreference;

const NOT_CHECKED = "not checked yet";
const STEPS = [
  ["secure-context", "Secure page (https)"],
  ["webxr", "WebXR (navigator.xr)"],
  ["immersive-ar", "AR sessions (immersive-ar)"],
  ["layers-api", "WebXR Layers API"],
  ["camera-permission", "Camera permission"],
  ["session", "AR session starts (from the tap)"],
  ["base-layer", "The page's own XRWebGLLayer as baseLayer"],
  ["tracking", "Tracking (viewer poses)"],
  ["camera", "Camera image (camera-access)"],
  ["camera-read", "Camera image read back (framebuffer blit)"],
  ["depth", "Depth (depth-sensing)"],
  ["upright", "Camera image stands upright"],
  ["live-ar", "Live AR on this phone"],
];

const report = {
  kind: "dronesim-check",
  version: 1,
  date: new Date().toISOString(),
  page: window.location.href,
  userAgent: navigator.userAgent,
  screen: {
    width: window.screen.width, height: window.screen.height, devicePixelRatio: window.devicePixelRatio,
    orientation: window.screen.orientation?.type ?? null, angle: window.screen.orientation?.angle ?? null,
  },
  steps: STEPS.map(([id, title]) => ({ id, title, status: "unknown", detail: NOT_CHECKED })),
  support: {},
  session: null,
  upright: { answer: null },
  errors: [],
};
const state = { phase: "support", report };
window.dronesimCheck = state;

function recordError(where, exc) {
  report.errors.push({ where, name: exc?.name ?? typeof exc, message: String(exc?.message ?? exc) });
  render();
}
window.addEventListener("error", (e) => recordError("page", e.error ?? { name: "Error", message: e.message }));
window.addEventListener("unhandledrejection", (e) => recordError("page (promise)", e.reason));

/** Set a step's line: status pass | fail | unknown | info, and what was seen. */
function step(id, status, detail) {
  Object.assign(report.steps.find((s) => s.id === id), { status, detail });
  render();
}

function render() {
  const list = $("#steps");
  list.replaceChildren(...report.steps.map((s) => {
    const li = document.createElement("li");
    li.dataset.step = s.id;
    li.dataset.status = s.status;
    const badge = document.createElement("span");
    badge.className = "badge";
    badge.textContent = s.status;
    const text = document.createElement("span");
    text.innerHTML = "<b></b><small></small>";
    text.querySelector("b").textContent = s.title;
    text.querySelector("small").textContent = s.detail;
    li.append(badge, text);
    return li;
  }));
  $("#report").textContent = JSON.stringify(report, null, 2);
}

/** Secure context, WebXR, immersive-ar, the Layers API: all known before any tap. */
async function checkSupport() {
  const s = report.support;
  s.secureContext = window.isSecureContext;
  step("secure-context", s.secureContext ? "pass" : "fail", s.secureContext ? "this page is a secure context" :
    "not a secure context: WebXR needs https. Start the server with --tls and open its https:// address.");
  s.webxr = Boolean(navigator.xr);
  if (!s.webxr && !s.secureContext) {
    step("webxr", "fail", "no WebXR (no navigator.xr): browsers hide it from pages that are not secure, see above");
    step("immersive-ar", "fail", "no WebXR, so no AR");
  } else if (!s.webxr) {
    step("webxr", "fail", "no WebXR in this browser (no navigator.xr). Live AR needs Chrome on an Android phone with " +
      "ARCore (Google Play Services for AR); on an iPhone, record with Stray Scanner or Record3D instead.");
    step("immersive-ar", "fail", "no WebXR, so no AR");
  } else {
    step("webxr", "pass", "navigator.xr is there");
    try {
      s.immersiveAr = await navigator.xr.isSessionSupported("immersive-ar");
      step("immersive-ar", s.immersiveAr ? "pass" : "fail", s.immersiveAr ? "isSessionSupported('immersive-ar') is true" :
        "isSessionSupported('immersive-ar') is false: no ARCore, or this browser offers no AR. You may still tap " +
        "Start: the error is recorded.");
    } catch (exc) {
      recordError("isSessionSupported", exc);
      step("immersive-ar", "unknown", `isSessionSupported threw ${exc.name}: ${exc.message}`);
    }
  }
  // Chrome 147+: three.js would take the layers path, where getCameraImage crashes; live AR and
  // this page own their XRWebGLLayer instead, so either answer is fine.
  s.layersApi = typeof XRWebGLBinding !== "undefined" && "createProjectionLayer" in XRWebGLBinding.prototype;
  step("layers-api", "info", s.layersApi ? "present (Chrome 147+): XRWebGLBinding.createProjectionLayer exists" :
    "absent: no XRWebGLBinding.createProjectionLayer");
  await checkCameraPermission();
  $("#btn-start").disabled = !s.webxr;
  state.phase = s.webxr ? "ready" : "done";
}

/** The camera permission's state: refused, AR runs without camera-access (no live AR). */
async function checkCameraPermission() {
  try {
    const { state: permission } = await navigator.permissions.query({ name: "camera" });
    report.support.cameraPermission = permission;
    const status = { granted: "pass", denied: "fail" }[permission] ?? "info";
    step("camera-permission", status, permission === "denied" ?
      "denied: allow the camera for this site in the browser's site settings, then check again" :
      `${permission}${permission === "prompt" ? ": the browser asks when AR starts" : ""}`);
  } catch (exc) {
    recordError("permissions.query camera", exc);
    step("camera-permission", "unknown", `cannot ask: ${exc.name}: ${exc.message}`);
  }
}

/** The AR session, started straight from the tap (requestSession needs the user's
 * activation: nothing may be awaited before it). */
async function runSession() {
  state.phase = "running";
  $("#btn-start").disabled = true;
  const overlay = $("#xr-overlay");
  let session;
  try {
    session = await navigator.xr.requestSession("immersive-ar", sessionOptions(overlay));
  } catch (exc) {
    recordError("requestSession", exc);
    step("session", "fail", `requestSession refused: ${exc.name}: ${exc.message}`);
    finish();
    return;
  }
  step("session", "pass", `started; enabled features: ${session.enabledFeatures?.join(", ") ?? "not reported"}`);
  overlay.hidden = false;
  const progress = (elapsed, probe) => {
    const depth = probe.depth.frames ? "depth is coming" : "no depth yet: move the phone slowly sideways";
    $("#xr-progress").textContent = `${(elapsed / 1000).toFixed(1)} s: ${probe.camera.distinct} camera images, ${depth}`;
  };
  const probe = new SessionProbe(session, recordError, progress);
  try {
    report.session = await probe.run();
  } catch (exc) {
    recordError("AR session set-up", exc);
    step("session", "fail", `started, but its set-up failed: ${exc.name}: ${exc.message}`);
    session.end().catch((e) => recordError("session.end", e));
  } finally {
    overlay.hidden = true;
  }
  if (report.session) describeSession(report.session, probe.uprightImage);
  finish();
}

function describeSession(r, uprightImage) {
  const seconds = ((r.durationMs ?? r.endedEarlyMs ?? 0) / 1000).toFixed(1);
  if (r.endedEarlyMs !== null) step("session", "fail", `the session ended after ${seconds} s, before the check was done`);
  step("base-layer", r.baseLayerIsXRWebGLLayer ? "pass" : "fail",
    `renderState.baseLayer ${r.baseLayerIsXRWebGLLayer ? "is" : "is not"} the page's XRWebGLLayer; framebuffer ` +
    `${r.view?.framebuffer?.join("x") ?? "?"}`);
  step("tracking", r.xr.framesWithPose > 0 ? "pass" : "fail",
    `${r.xr.frames} XR frames in ${seconds} s (${r.xr.fps} fps), ${r.xr.framesWithPose} with a viewer pose, ` +
    `${r.xr.viewCount ?? 0} view(s)`);
  const c = r.camera;
  const cameraAsked = r.enabledFeatures === null || r.enabledFeatures.includes("camera-access");
  step("camera", c.framesWithImage > 0 ? "pass" : "fail", c.framesWithImage > 0 ?
    `${c.width}x${c.height}, ${c.distinctImages} new images (${c.fps} fps) in ${c.framesWithImage} frames with one` :
    cameraAsked ? "camera-access was granted but no frame had a camera image" :
      "camera-access not granted (the camera permission refused, or no raw camera access in this browser)");
  const readError = report.errors.find((e) => e.where === "camera image read-back");
  step("camera-read", c.uprightImageSize ? "pass" : c.framesWithImage ? "fail" : "unknown", c.uprightImageSize ?
    `read back at ${c.uprightImageSize.join("x")} (${c.readMsMean} ms per read)` :
    readError ? `${readError.name}: ${readError.message}` : "no camera image to read");
  const d = r.depth;
  if (d.frames > 0) {
    step("depth", "pass", `${r.depthUsage}, ${r.depthDataFormat}, ${d.width}x${d.height}, rawValueToMeters ` +
      `${d.rawValueToMeters}; first after ${d.firstAfterMs} ms, then ${d.fps} new images/s ` +
      `(${d.perCameraImage ?? "?"} per camera image); ${Math.round((d.zeroFraction ?? 0) * 100)} % zero`);
  } else {
    const enabled = r.enabledFeatures === null || r.enabledFeatures.includes("depth-sensing");
    step("depth", "fail", enabled ? `depth-sensing enabled (${r.depthUsage}, ${r.depthDataFormat}) but no depth in ` +
      `${seconds} s: move the phone slowly sideways over a lit, textured place` :
      "depth-sensing not granted: this phone's ARCore gives the web no depth");
  }
  if (uprightImage) showUpright(uprightImage);
  else step("upright", "unknown", "no camera image to show");
}

/** The upright question: the last camera image beside an arrow pointing up. */
function showUpright(image) {
  step("upright", "unknown", "not answered yet: does the picture stand the same way as the room?");
  const canvas = $("#upright-image");
  canvas.width = image.width;
  canvas.height = image.height;
  canvas.getContext("2d").putImageData(image, 0, 0);
  $("#upright").hidden = false;
}

function answerUpright(answer) {
  report.upright = { answer, imageSize: report.session.camera.uprightImageSize };
  step("upright", answer === "yes" ? "pass" : "fail", answer === "yes" ? "the user saw the picture upright" :
    "the user saw the picture turned: the camera image does not stand as the screen (a sensor mounted at 90 or " +
    "270 degrees the browser did not turn?)");
  verdict();
}

/** Why live AR cannot run here, from what it asks (LIVE_DEPTH_*) and what was seen; null
 * when nothing stands in its way (so far). */
function liveBlocker() {
  const s = report.session;
  const failed = (id) => report.steps.find((x) => x.id === id).status === "fail";
  if (!report.support.secureContext) return "the page is not secure (https)";
  if (!report.support.webxr) return "no WebXR";
  if (!s) {
    if (failed("session")) return "no AR session";
    return report.support.immersiveAr === false ? "this browser offers no AR (immersive-ar)" : null;
  }
  if (s.depth.frames === 0) return "no depth";
  if (s.depthUsage !== LIVE_DEPTH_USAGE || !LIVE_DEPTH_FORMATS.includes(s.depthDataFormat)) {
    return `depth is ${s.depthUsage} ${s.depthDataFormat}; live AR asks for ${LIVE_DEPTH_USAGE} ${LIVE_DEPTH_FORMATS.join(" or ")}`;
  }
  if (s.camera.framesWithImage === 0) {
    return report.support.cameraPermission === "denied" ? "the camera permission is denied" : "no camera image";
  }
  if (failed("camera-read")) return "the camera image cannot be read back";
  if (report.upright.answer === "no") return "the camera image is not upright";
  return null;
}

function verdict() {
  const why = liveBlocker();
  if (why) step("live-ar", "fail", `live AR cannot work here: ${why}. Download the report and send it to us.`);
  else if (!report.session) step("live-ar", "unknown", "tap Start to check the AR session");
  else step("live-ar", "pass", "everything live AR needs is there");
}

function finish() {
  for (const s of report.steps) if (s.detail === NOT_CHECKED) s.detail = "not checked: no AR session ran";
  verdict();
  state.phase = "done";
  render();
}

function download() {
  const blob = new Blob([JSON.stringify(report, null, 2)], { type: "application/json" });
  const a = document.createElement("a");
  a.href = URL.createObjectURL(blob);
  a.download = `dronesim-check-${report.date.slice(0, 19).replace(/[:T]/g, "-")}.json`;
  a.click();
  setTimeout(() => URL.revokeObjectURL(a.href), 10_000);
}

$("#btn-start").addEventListener("click", () => runSession());
$("#btn-upright-yes").addEventListener("click", () => answerUpright("yes"));
$("#btn-upright-no").addEventListener("click", () => answerUpright("no"));
$("#btn-download").addEventListener("click", download);
$("#measure-s").textContent = `${MEASURE_MS / 1000}`;
$("#max-s").textContent = `${MAX_MS / 1000}`;
render();
checkSupport().then(verdict).catch((exc) => recordError("support check", exc)).finally(() => {
  if (state.phase === "done") finish();
});
