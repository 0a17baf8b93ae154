// The page's animation frame: each view draws while its layout shows it (the render budget says
// how often), the flight replay and the course clock move on, the map's mesh is fetched while a
// view wants it, and the HUD's rates are refreshed four times a second (a stream that runs
// behind its rate makes the views draw less often).

const MESH_AFTER_NO_DEPTH_MS = 1000; // live AR without depth this long: occlusion by the map's mesh
const HUD_EVERY_MS = 250;

/**
 * Run the loop for good.
 * @param {object} p the page's parts: views (ar, map, fpv), mapMesh, flights, course, hud,
 *   budget (render_budget.js), load (page_load.js), client, state (session/state.js) and
 *   control (session/control.js: its source and streamer)
 */
export function startRenderLoop({ ar, map, fpv, mapMesh, flights, course, hud, budget, load, client, state, control }) {
  let lastHud = 0;
  const frame = (now) => {
    const view = document.body.classList;
    const fpvShown = view.contains("layout-fpv");
    // Live AR draws in its XR session's own frames (capture/sources/live.js).
    if (!view.contains("layout-map") && !fpvShown && !control.source?.session) ar.tick(now);
    if (!view.contains("layout-ar") && !fpvShown) map.tick(now);
    if (fpvShown) fpv.tick(now);
    flights.tick(now);
    course.tick(now);
    // The mesh is fetched only while a view draws it: FPV, or live AR's occlusion when the XR
    // frames have had no depth for a while (not for one frame without it).
    const noDepth = ar.occlusion.depthMissingSince;
    mapMesh.wanted = fpvShown || (ar.occlusion.enabled && control.source?.kind === "live" &&
      noDepth !== null && now - noDepth > MESH_AFTER_NO_DEPTH_MS);
    mapMesh.poll(now);
    if (now - lastHud > HUD_EVERY_MS) {
      lastHud = now;
      const streamer = control.streamer;
      const waits = hud.rates({ latencyMs: client.latencyMs, clientSkipped: streamer?.skipped ?? 0,
        serverDropped: state.seen.serverDropped, askedFps: streamer?.running ? streamer.fps : 0,
        load: load.summary(now) });
      budget.streamBehind = waits !== null; // then the views draw less often
    }
    budget.update(now);
    requestAnimationFrame(frame);
  };
  requestAnimationFrame(frame);
}
