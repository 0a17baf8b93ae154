// The page's buttons: the layout (AR, both, map, FPV), Start/Stop, the drone's take-off, hold
// and land, the map's Fit and colour, AR occlusion, and the map download. A viewer link's page
// has them all off.

const $ = (selector) => document.querySelector(selector);
const LAYOUTS = ["ar", "split", "map", "fpv"];

/** Show one layout: "ar", "split" (AR and map), "map" or "fpv". */
export function setView(view) {
  document.body.classList.remove(...LAYOUTS.map((name) => `layout-${name}`));
  document.body.classList.add(`layout-${view}`);
  for (const button of document.querySelectorAll("[data-view]")) {
    button.setAttribute("aria-pressed", String(button.dataset.view === view));
  }
}

/** Real surfaces hide the drone in AR (views/occlusion.js), or the drone is drawn on top. */
export function setOcclusion(ar, on) {
  ar.occlusion.enabled = on;
  ar.dirty = true;
  $("#btn-occlusion").setAttribute("aria-pressed", String(on));
}

/**
 * Wire the buttons.
 * @param {{control: import("../session/control.js").SessionControl, pilot: import("./pilot.js").Pilot,
 *   map: import("../views/map_view.js").MapView, ar: import("../views/ar_view.js").ARView,
 *   hud: import("./hud.js").Hud, resumeOptions: () => object}} parts resumeOptions: what Start
 *   starts when there is no stream to go on with (the Setup dialog's choice)
 */
export function wireControls({ control, pilot, map, ar, hud, resumeOptions }) {
  const stream = $("#btn-stream");
  stream.addEventListener("click", () => (control.streamer?.running ? control.stopStreaming() : control.resume(resumeOptions())));
  control.addEventListener("busy", ({ detail }) => (stream.disabled = detail.busy));
  control.addEventListener("streaming", ({ detail: { running, reason } }) => {
    stream.textContent = running ? "Stop" : "Start";
    stream.classList.toggle("danger", running);
    stream.classList.toggle("primary", !running);
    if (!running && reason) hud.toast(`streaming stopped: ${reason}`, "warn");
  });
  $("#btn-takeoff").addEventListener("click", () => pilot.takeoff());
  $("#btn-hold").addEventListener("click", () => pilot.hold());
  $("#btn-land").addEventListener("click", () => pilot.land());
  $("#btn-download").addEventListener("click", () => downloadMap(control.client, hud));
  $("#btn-fit").addEventListener("click", () => map.fit());
  $("#btn-colour").addEventListener("click", (e) => {
    const mode = map.colourMode === "height" ? "rgb" : "height";
    map.setColourMode(mode);
    e.target.textContent = mode === "height" ? "Height" : "Colour";
  });
  $("#btn-occlusion").addEventListener("click", () => setOcclusion(ar, !ar.occlusion.enabled));
  for (const button of document.querySelectorAll("[data-view]")) {
    button.addEventListener("click", () => setView(button.dataset.view));
  }
  pilot.addEventListener("refused", (e) => hud.toast(`command refused here: ${e.detail.message}`, "error"));
  setView(document.body.className.replace("layout-", "") || "split");
}

/** A viewer link's page: every control off (the map shows). */
export function disableControls() {
  document.body.classList.add("viewing");
  for (const button of document.querySelectorAll("#controls button, #btn-flights")) button.disabled = true;
  setView("map");
}

/** Save the session's fused map (PLY) as a file. */
export async function downloadMap(client, hud) {
  try {
    const { blob, filename } = await client.downloadMap();
    const url = URL.createObjectURL(blob);
    const a = document.createElement("a");
    a.href = url;
    a.download = filename;
    document.body.append(a);
    a.click();
    a.remove();
    setTimeout(() => URL.revokeObjectURL(url), 10000);
    hud.toast(`map saved as ${filename} (${(blob.size / 1e6).toFixed(1)} MB)`, "ok");
  } catch (exc) {
    hud.toast(exc.message, "error", 6000);
  }
}
