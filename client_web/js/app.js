// The page: wires the protocol, the session's socket and state, the session control (capture
// source and streamer), the AR, map and FPV views, the HUD and the pilot's controls. What each
// part does lives in its own module: network/ (the socket, the protocol), capture/ (sources,
// streamer, packing), session/ (state, control), views/, ui/, formats/. `window.dronesim`
// exposes the app (and a JSON snapshot of what it saw) for debugging and the browser tests.

import { SessionClient, State } from "./network/connection.js";
import { PageLoad } from "./network/page_load.js";
import { Protocol } from "./network/protocol.js";
import { joinLink } from "./network/session_rest.js";
import { ViewerClient, viewerLink } from "./network/viewer.js";
import { SessionControl } from "./session/control.js";
import { pageSnapshot } from "./session/snapshot.js";
import { SessionState } from "./session/state.js";
import { disableControls, downloadMap, setOcclusion, setView, wireControls } from "./ui/controls.js";
import { FlightsPanel } from "./ui/flights_panel.js";
import { Hud } from "./ui/hud.js";
import { Invite } from "./ui/invite.js";
import { showPhoneLink } from "./ui/phone_link.js";
import { Pilot } from "./ui/pilot.js";
import { RoomHud } from "./ui/room_hud.js";
import { SetupDialog, uploadRecording } from "./ui/setup_dialog.js";
import { Taps } from "./ui/taps.js";
import { ARView } from "./views/ar_view.js";
import { CourseView } from "./views/course_view.js";
import { FPVView } from "./views/fpv_view.js";
import { FrameDepths } from "./views/frame_depths.js";
import { MapMesh } from "./views/map_mesh.js";
import { MapView } from "./views/map_view.js";
import { RenderBudget, softwareWebGL } from "./views/render_budget.js";
import { startRenderLoop } from "./views/render_loop.js";

const $ = (selector) => document.querySelector(selector);

class App {
  async init() {
    const params = new URLSearchParams(window.location.search);
    this.hud = new Hud();
    this.protocol = await Protocol.load();
    const watch = viewerLink(); // a viewer link (#watch=...): this page only watches
    // An invitation (#join=...): this page's session joins the inviting session's shared room.
    this.client = watch ? new ViewerClient(this.protocol, watch) : new SessionClient(this.protocol, { join: joinLink() });
    // The page's own main-thread work, and what the views may draw (render_budget.js).
    this.load = new PageLoad();
    this.state = new SessionState(this.client, { meter: this.load });

    // The pilot's controls, and the views (a tap on the AR picture or the map sends the drone).
    this.pilot = new Pilot(this.client, { left: $("#stick-left"), right: $("#stick-right"), modes: $("#flight-mode") });
    this.taps = new Taps({ pilot: this.pilot, hud: this.hud });
    this.ar = new ARView($("#ar-view"), { onTap: (pixel, seq) => this.taps.ar(pixel, seq) });
    this.map = new MapView($("#map-view"), { onPick: (picked) => this.taps.map(picked) });
    this.fpv = new FPVView($("#fpv-view"), { points: this.map.geometry }); // the map's points until the mesh comes
    this.budget = new RenderBudget({ frameMs: Number(params.get("frameBudgetMs")) || undefined,
      software: softwareWebGL(this.ar.renderer) });
    for (const view of [this.ar, this.map, this.fpv]) Object.assign(view, { budget: this.budget, meter: this.load });
    this.mapMesh = new MapMesh(this.client); // the fused mesh, for FPV and occlusion without depth
    this.frameDepths = new FrameDepths(this.ar);

    // Session control, the course and the dialogs.
    this.control = new SessionControl({ client: this.client, state: this.state, protocol: this.protocol, hud: this.hud,
      ar: this.ar, frameDepths: this.frameDepths, meter: this.load, upload: (file) => uploadRecording(file, this.hud),
      setView: (view) => this.setView(view) });
    this.course = new CourseView({ client: this.client, state: this.state, ar: this.ar, map: this.map, hud: this.hud });
    this.flights = new FlightsPanel({ client: this.client, map: this.map, hud: this.hud, setView: (view) => this.setView(view) });
    this.setup = new SetupDialog(this.control, this.hud);
    this.roomHud = new RoomHud({ client: this.client }); // a shared room's pilots
    this.invite = new Invite({ client: this.client, hud: this.hud });

    // Everything that shows the session follows its state. The map first: the AR view reads
    // its floor height after each map update; taps before the HUD: an error they handle is not shown.
    this.map.follow(this.state);
    this.ar.follow(this.state, { imageFor: (seq) => this.control.takeImage(seq), groundHeight: () => this.map.groundHeight(),
      mesh: this.mapMesh });
    this.fpv.follow(this.state, { mesh: this.mapMesh });
    this.mapMesh.follow(this.state);
    this.frameDepths.follow(this.state);
    this.pilot.follow(this.state);
    this.flights.follow(this.state);
    this.taps.follow(this.state);
    this.hud.follow(this.state);
    this.roomHud.follow(this.state);

    wireControls({ control: this.control, pilot: this.pilot, map: this.map, ar: this.ar, hud: this.hud,
      resumeOptions: () => this.setup.choice() });
    startRenderLoop(this);
    this.hud.connection(State.IDLE);
    if (!watch) showPhoneLink($("#ar-view")); // desktop-size pages: a QR code until frames show
    if (params.get("view")) this.setView(params.get("view"));
    if (params.get("occlusion") === "off") this.setOcclusion(false);
    this.setup.preselect(params.get("mode")); // a capture mode: demo, demo-small, folder, live...
    this.setup.checkLive({ chosen: params.get("mode"), hasSession: Boolean(this.client.session) });
    if (watch) return this.#watch();
    if (params.get("autostart")) {
      this.start({ mode: params.get("autostart"), fps: Number(params.get("fps") || 15) }).catch(() => {});
    }
  }

  /** A viewer link's page: the map and the drone live, every control off. */
  #watch() {
    disableControls();
    this.client.addEventListener("welcome", () => this.state.reset()); // the server resends the map
    this.client.open();
    this.hud.toast("watching a session (read-only)", "info", 6000);
  }

  // What the tests and debugging read and call (window.dronesim).
  get streamer() {
    return this.control.streamer;
  }

  get source() {
    return this.control.source;
  }

  get hello() {
    return this.control.hello;
  }

  get seen() {
    return this.state.seen;
  }

  get liveSupport() {
    return this.setup.support;
  }

  start(options) {
    return this.control.start(options);
  }

  stopStreaming(reason = "") {
    this.control.stopStreaming(reason);
  }

  resume() {
    this.control.resume(this.setup.choice());
  }

  setView(view) {
    setView(view);
  }

  setOcclusion(on) {
    setOcclusion(this.ar, on);
  }

  downloadMap() {
    return downloadMap(this.client, this.hud);
  }

  snapshot() {
    return pageSnapshot(this);
  }
}

const app = new App();
window.dronesim = app;
app.ready = app.init().catch((exc) => {
  console.error(exc);
  document.body.insertAdjacentHTML("afterbegin", `<p class="error" style="padding:12px">The page could not start: ${exc.message}</p>`);
});
