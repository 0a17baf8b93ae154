// What the page saw, as plain data: the browser tests and debugging read it through
// window.dronesim.snapshot(). Read-only: it changes nothing on the page.

/** @param {object} app the page's parts (app.js): client, control, state, views, hud, pilot... */
export function pageSnapshot(app) {
  const { client, control, ar, fpv, map, mapMesh, frameDepths, budget, load, hud, pilot, flights, course } = app;
  const streamer = control.streamer;
  const rect = ar.stage.getBoundingClientRect();
  const trail = map.trajectory;
  return {
    connection: client.state,
    session: client.session?.id ?? null,
    streaming: streamer?.running ?? false,
    sent: client.counts.sent,
    counts: { ...client.counts },
    statusLog: client.statusLog.map(({ state, message }) => ({ state, message })),
    skipped: streamer?.skipped ?? 0,
    unavailable: { ...(streamer?.unavailable ?? {}) },
    heldBack: streamer?.heldBack ?? false,
    heldBackMs: streamer?.heldBackMs ?? 0,
    inFlight: client.inFlight.size,
    latencyMs: client.latencyMs,
    hello: control.hello ?? null,
    recordingStatus: document.querySelector("#recording-status")?.textContent ?? "",
    ...app.seen,
    ar: { ...ar.lastDraw, stage: { left: rect.left, top: rect.top, width: rect.width, height: rect.height },
      intrinsics: ar.intrinsics, colourSize: ar.colourSize, shownSeq: ar.frame?.seq ?? null },
    occlusion: { enabled: ar.occlusion.enabled, source: ar.lastDraw.occlusion ?? "none", boxes: ar.lastDraw.occlusionBoxes ?? 0,
      depthSeq: ar.occlusion.depth?.seq ?? null, depthFailures: frameDepths.failures,
      depthReads: frameDepths.reads },
    fpv: { ...fpv.lastDraw }, mesh: mapMesh.summary(), budget: budget.summary(),
    load: load.summary(), waitsFor: hud.waits.shown ? hud.waits.last?.name ?? null : null,
    trail: { points: trail.count, last: trail.count ? Array.from(trail.array.subarray(3 * trail.count - 3, 3 * trail.count)) : null },
    commands: pilot.log.map(({ id, name, fields }) => ({ id, name, fields })),
    liveSupport: app.liveSupport ?? null,
    viewer: client.viewer === true,
    ...flights.snapshot(),
    course: course.snapshot(),
    // A shared room: its pilots, and the other pilots' drones drawn (AR: with their pixels).
    room: { ...app.roomHud.snapshot(), others_drawn: map.others.drones.size, ar_others: ar.lastDraw.others ?? [],
      map_others: map.others.drawn(), fpv_others: fpv.lastDraw.others ?? [], map_cameras: map.others.camerasDrawn(), map_routes: map.others.routesDrawn(), invite: app.invite.link,
      started_race: app.invite.race_ },
  };
}
