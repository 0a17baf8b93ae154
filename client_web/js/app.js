// The page: wires the protocol, the session, a capture source (replay or live WebXR), the AR
// and map views, the HUD and the pilot's controls. `window.dronesim` exposes the app (and a
// JSON snapshot of what it saw) for debugging and the browser tests.

import { ARView } from "./ar_view.js";
import { SessionClient, State } from "./connection.js";
import { FPVView } from "./fpv_view.js";
import { FrameDepths } from "./frame_depths.js";
import { CourseView } from "./course_view.js";
import { upFromGravity } from "./geometry.js";
import { Hud } from "./hud.js";
import { PageLoad } from "./page_load.js";
import { RenderBudget, softwareWebGL } from "./render_budget.js";
import { MapMesh } from "./map_mesh.js";
import { MapView } from "./map_view.js";
import { Pilot } from "./pilot.js";
import { parsePly, parseTumPositions } from "./ply.js";
import { mapChunkArrays, Protocol } from "./protocol.js";
import { LiveSource, liveSupport } from "./sources/live.js";
import { ReplaySequence, ReplaySource } from "./sources/replay.js";
import { Streamer } from "./streamer.js";
import { FlightsPanel } from "./flights_panel.js";
import { ViewerClient, viewerLink } from "./viewer.js";
import { showPhoneLink } from "./phone_link.js";

const $ = (selector) => document.querySelector(selector);
const REPLAY_KEY = "dronesim.replay"; // where a replay was, to go on there after a reload
const MESH_AFTER_NO_DEPTH_MS = 1000; // live AR without depth this long: occlusion by the map's mesh
const EVENT_KINDS = { spawned: "ok", arrived: "ok", landed: "info", replanned: "info", blocked: "warn", collision: "warn",
  crash: "error" };
// The server's demo sequences (routes_client.py DEMO_PRESETS), by capture mode.
const DEMO_URLS = { demo: "/api/demo", "demo-small": "/api/demo?preset=small", "demo-loop": "/api/demo?preset=loop" };
const COURSE_EVENTS = new Set(["gate_passed", "gate_missed", "course_finished"]); // course_view.js shows them

class App {
  async init() {
    this.hud = new Hud();
    this.protocol = await Protocol.load();
    const watch = viewerLink(); // a viewer link (#watch=...): this page only watches
    this.client = watch ? new ViewerClient(this.protocol, watch) : new SessionClient(this.protocol);
    this.ar = new ARView($("#ar-view"), { onTap: (pixel, seq) => this.#tapAR(pixel, seq) });
    this.map = new MapView($("#map-view"), { onPick: (picked) => this.#tapMap(picked) });
    this.fpv = new FPVView($("#fpv-view"), { points: this.map.geometry }); // the map's points until the mesh comes
    // The page's own main-thread work, and what the views may draw (render_budget.js).
    this.load = new PageLoad();
    this.budget = new RenderBudget({ frameMs: Number(new URLSearchParams(window.location.search).get("frameBudgetMs")) ||
      undefined, software: softwareWebGL(this.ar.renderer) });
    for (const view of [this.ar, this.map, this.fpv]) Object.assign(view, { budget: this.budget, meter: this.load });
    this.mapMesh = new MapMesh(this.client); // the fused mesh, for FPV and occlusion without depth
    this.mapMesh.addEventListener("mesh", ({ detail: geometry }) => {
      this.fpv.setMesh(geometry);
      this.ar.occlusion.setMesh(geometry);
      this.ar.dirty = true;
    });
    this.frameDepths = new FrameDepths(this.ar);
    this.pilot = new Pilot(this.client, { left: $("#stick-left"), right: $("#stick-right"), modes: $("#flight-mode") });
    this.course = new CourseView({ client: this.client, ar: this.ar, map: this.map, hud: this.hud });
    this.streamer = null;
    this.source = null;
    this.seen = this.#emptySeen();
    this.tapCommands = new Set(); // ids of goto commands from taps: unreachable ones retry the nearest point
    this.#wireClient();
    this.#wireControls();
    this.flights = new FlightsPanel(this);
    this.#renderLoop();
    this.#setupDialog();
    this.hud.connection(State.IDLE);
    if (!watch) showPhoneLink($("#ar-view")); // desktop-size pages: a QR code until frames show
    const params = new URLSearchParams(window.location.search);
    if (params.get("view")) this.setView(params.get("view"));
    if (params.get("occlusion") === "off") this.setOcclusion(false);
    const mode = params.get("mode"); // preselect a capture mode: demo, demo-small, folder, live
    const radio = mode && document.querySelector(`input[name="mode"][value="${CSS.escape(mode)}"]`);
    if (radio && !radio.disabled) radio.checked = true;
    if (watch) return this.#watch();
    if (params.get("autostart")) {
      this.start({ mode: params.get("autostart"), fps: Number(params.get("fps") || 15) }).catch(() => {});
    }
  }

  /** A viewer link's page: the map and the drone live, every control off. */
  #watch() {
    document.body.classList.add("viewing");
    for (const button of document.querySelectorAll("#controls button, #btn-flights")) button.disabled = true;
    this.setView("map");
    this.client.addEventListener("welcome", () => this.#resetViews()); // the server resends the map
    this.client.open();
    this.hud.toast("watching a session (read-only)", "info", 6000);
  }

  #emptySeen() {
    return { poses: 0, states: {}, recovery: {}, lastPose: null, droneStates: 0, lastDrone: null, modeLog: [], events: [], errors: [],
      chunks: 0, chunkPoints: 0, mapPoints: 0, serverDropped: 0, serverFailures: {}, shownSeq: null, corrections: [], mapResets: 0 };
  }

  // ---- session and streaming --------------------------------------------------------------------

  /**
   * Start streaming from a capture mode into a session.
   * @param {{mode?: "demo"|"demo-small"|"demo-loop"|"folder"|"iphone"|"live", fps?: number, fresh?: boolean,
   *   room?: boolean, loops?: boolean, files?: FileList, recording?: File}} options
   *   loops: a new session closes loops (the server's setting otherwise); the demo there and
   *   back always starts a new session that does, as showing it is what it is for.
   */
  async start({ mode = "demo", fps = 15, fresh = false, room = false, loops = false, files = null, recording = null } = {}) {
    if (mode === "demo-loop") [fresh, loops] = [true, true];
    this.stopStreaming();
    this.source?.stop?.();
    const button = $("#btn-stream");
    button.disabled = true;
    try {
      let source;
      if (mode === "live") {
        if (navigator.userActivation && !navigator.userActivation.isActive) {
          // A browser starts AR only from the user's tap (e.g. ?autostart=live): ask for it.
          document.querySelector('input[name="mode"][value="live"]').checked = true;
          this.hud.showBanner("Tap Start to begin live AR (a browser starts AR only from a tap).", "info", 30000);
          return;
        }
        this.hud.hideBanner();
        source = new LiveSource(this.ar, $("#overlay-root"));
        source.onEnd = () => this.stopStreaming("AR ended");
        this.hud.toast("starting AR…");
        this.setView("ar"); // the camera fills the screen; the Map button overlays the map
        source.info = await source.start();
      } else {
        if (mode in DEMO_URLS) this.hud.toast("loading the demo sequence (the server makes it on first use, up to a minute)…");
        let sequence;
        if (mode === "folder") sequence = await ReplaySequence.fromFiles(files);
        else if (mode === "iphone") sequence = await this.#uploadRecording(recording);
        else sequence = await ReplaySequence.fromServer(DEMO_URLS[mode] ?? DEMO_URLS.demo);
        source = new ReplaySource(sequence);
        source.prefetch(0);
      }
      this.source = source;
      const info = source.info;
      const hello = this.protocol.hello(info);
      const { id, resumed } = await this.client.open(hello, { fresh, room, loopClosure: loops || null });
      if (!resumed) this.#resetViews();
      this.hud.toast(resumed ? `continuing session ${id}` : `new session ${id}`, "ok");
      this.hello = hello;
      this.ar.setCamera(info.intrinsics, info.colourSize);
      const up = upFromGravity(info.gravity);
      this.ar.setUp(up);
      this.map.setUp(up);
      if (resumed && this.map.pointCount === 0) this.#restoreMap();
      // A recording waits for the server rather than dropping frames; a live camera cannot.
      this.streamer = new Streamer(this.client, source, { fps, holdBack: source.kind === "replay", meter: this.load });
      // A replay reopened into its session goes on where it was: the camera does not jump.
      const place = JSON.parse(sessionStorage.getItem(REPLAY_KEY) ?? "null");
      if (resumed && source.kind === "replay" && place?.session === id && place.name === source.sequence.name) {
        this.streamer.tick = place.tick;
      }
      this.streamer.addEventListener("sent", (e) => this.frameDepths.keep(e.detail.seq, e.detail.fields));
      this.streamer.addEventListener("sent", () => sessionStorage.setItem(REPLAY_KEY, JSON.stringify(
        { session: id, name: source.sequence?.name, tick: this.streamer.tick })));
      this.streamer.addEventListener("state", (e) => this.#streamingChanged(e.detail));
      this.streamer.addEventListener("failure", (e) => this.hud.toast(`capture failed: ${e.detail.message}`, "error", 8000));
      this.streamer.start();
    } catch (exc) {
      console.error(exc);
      this.hud.showBanner(exc.message, "error", 10000);
      if (mode === "live") $("#live-status").textContent = exc.message; // stays in Setup, too
      this.#streamingChanged({ running: false });
      throw exc;
    } finally {
      button.disabled = false;
    }
  }

  /** Upload an iPhone recording for the server to convert, saying how far it got. */
  async #uploadRecording(file) {
    if (!file) throw new Error("pick a recording first (.r3d, or a Stray Scanner export zipped)");
    const status = $("#recording-status");
    const say = (text) => {
      status.textContent = text;
      this.hud.toast(text, "info", 3000);
    };
    say(`uploading ${file.name} (${(file.size / 1e6).toFixed(1)} MB)…`);
    let shown = -1;
    try {
      const sequence = await ReplaySequence.fromUpload(file, (stage, fraction) => {
        const percent = Math.floor(fraction * 100);
        if (stage === "upload" && percent >= shown + 10) {
          shown = percent;
          status.textContent = `uploading ${file.name}: ${percent} %`;
        } else if (stage === "convert") {
          status.textContent = fraction < 1 ? "converting on the server…" : "converted";
        }
      });
      const posed = sequence.frames.filter((f) => f.T_device_camera).length;
      say(`${sequence.name}: ${sequence.length} frames, ${posed} with the phone's pose`);
      this.recordingStatus = status.textContent;
      return sequence;
    } catch (exc) {
      status.textContent = exc.message;
      throw exc;
    }
  }

  /** A page reopened into a running session: the map and trajectory made so far, from the
   * session's downloads (map_chunk messages only bring new points). */
  async #restoreMap() {
    try {
      const [{ blob: ply }, { blob: tum }] = await Promise.all([this.client.download("map.ply"),
        this.client.download("trajectory.tum")]);
      const { points, colours } = parsePly(await ply.arrayBuffer());
      this.map.addPoints(points, colours);
      for (const p of parseTumPositions(await tum.text())) this.map.addTrajectoryPoint(p);
      this.seen.mapPoints = this.map.pointCount;
      this.hud.points(this.map.pointCount);
      this.ar.setGroundHeight(this.map.groundHeight());
    } catch (exc) {
      console.info("no earlier map to show", exc.message);
    }
  }

  stopStreaming(reason = "") {
    this.streamer?.stop(reason);
  }

  resume() {
    if (this.streamer) this.streamer.start();
    else this.start(this.#dialogChoice()).catch(() => {}); // shown in the banner
  }

  #resetViews() {
    this.map.clear();
    this.mapMesh.clear();
    this.ar.clearDrone();
    this.map.setDroneState(null);
    this.course.clear();
    this.seen = this.#emptySeen();
    this.hud.drone(null);
  }

  #streamingChanged({ running, reason }) {
    const button = $("#btn-stream");
    button.textContent = running ? "Stop" : "Start";
    button.classList.toggle("danger", running);
    button.classList.toggle("primary", !running);
    if (!running && reason) this.hud.toast(`streaming stopped: ${reason}`, "warn");
  }

  #wireClient() {
    const c = this.client;
    c.addEventListener("status", ({ detail }) => {
      this.hud.connection(detail.state, detail.message);
      if (detail.state === State.RECONNECTING) this.hud.showBanner(`Connection lost: ${detail.message}`, "warn", 0);
      else if (detail.state === State.OPEN) this.hud.hideBanner();
      else if (detail.state === State.TAKEN_OVER) {
        this.stopStreaming("the session moved to another tab or device");
        this.hud.showBanner("Another tab or device took this session over. Start takes it back.",
          "warn", 0);
      } else if (detail.state === State.ENDED) {
        this.stopStreaming("the session ended");
        this.hud.showBanner(`${detail.message}. Start again for a new session.`, "error", 0);
        this.client.forget();
        this.streamer = null;
      }
    });
    c.addEventListener("pose", ({ detail: pose }) => this.load.time("receive", () => this.#pose(pose)));
    c.addEventListener("map_chunk", ({ detail: chunk }) => {
      const { points, colours } = mapChunkArrays(chunk);
      this.map.addPoints(points, colours, chunk.reset === true);
      this.mapMesh.noteMapPoints(this.map.pointCount, chunk.reset === true);
      this.seen.chunks += 1;
      if (chunk.reset === true) this.seen.mapResets += 1;
      this.seen.chunkPoints += chunk.count;
      this.seen.mapPoints = this.map.pointCount;
      this.hud.points(this.map.pointCount);
      this.ar.setGroundHeight(this.map.groundHeight());
    });
    c.addEventListener("map_corrected", ({ detail: correction }) => this.#mapCorrected(correction));
    c.addEventListener("drone_state", ({ detail: state }) => {
      this.seen.droneStates += 1;
      if (this.seen.lastDrone?.mode !== state.mode) {
        this.seen.modeLog.push({ mode: state.mode, command_id: state.command_id ?? null });
        if (this.seen.modeLog.length > 100) this.seen.modeLog.shift();
      }
      this.seen.lastDrone = state;
      this.ar.setDroneState(state);
      this.map.setDroneState(state);
      this.fpv.setDroneState(state);
      this.hud.drone(state);
      this.pilot.serverMode(state.flight_mode);
      this.flights?.droneState(state);
    });
    c.addEventListener("drone_event", ({ detail: event }) => {
      this.seen.events.push(event);
      if (this.seen.events.length > 200) this.seen.events.shift();
      const where = event.position.map((v) => v.toFixed(2)).join(", ");
      if (COURSE_EVENTS.has(event.event)) return;
      if (event.event === "crash") this.hud.showBanner(`Crash! ${event.message} (at ${where} m)`, "error", 6000);
      else if (event.event === "collision") this.hud.showBanner(`Bump! ${event.message} (at ${where} m)`, "warn", 3000);
      else if (event.event === "blocked") this.hud.showBanner(`Route blocked: ${event.message}`, "warn", 4000);
      this.hud.toast(`${event.event}: ${event.message}`, EVENT_KINDS[event.event] ?? "info");
    });
    c.addEventListener("error", ({ detail: error }) => this.#serverError(error));
  }

  #pose(pose) {
    const s = this.seen;
    s.poses += 1;
    s.states[pose.state] = (s.states[pose.state] ?? 0) + 1;
    if (pose.recovery) s.recovery[pose.recovery] = (s.recovery[pose.recovery] ?? 0) + 1;
    s.lastPose = { seq: pose.seq, timestamp: pose.timestamp, state: pose.state, inliers: pose.inliers, T_world_camera: pose.T_world_camera,
      recovery: pose.recovery ?? null };
    s.serverDropped = pose.dropped;
    s.serverFailures = pose.failures ?? {};
    this.hud.pose(pose, this.client.lastLatencyMs);
    this.map.addCameraPose(pose.T_world_camera);
    const bitmap = this.streamer?.takeImage(pose.seq) ?? null;
    this.ar.showFrame(bitmap, pose.seq, pose.T_world_camera, pose.state, pose.recovery);
    this.frameDepths.shown(pose.seq);
    bitmap?.close?.();
    s.shownSeq = pose.seq;
  }

  /** The server closed a loop: its keyframes moved, and the map is re-fused (the chunks that
   * follow start with reset). Poses from correction.from_seq on are in the corrected world;
   * the trail is redrawn through the corrected keyframes, as the poses before are not resent. */
  #mapCorrected(correction) {
    const s = this.seen;
    s.corrections.push({ loops: correction.loops, from_seq: correction.from_seq, keyframes: correction.keyframes.length });
    if (s.corrections.length > 50) s.corrections.shift();
    this.map.replaceTrajectory(correction.keyframes.map((k) => k.T_world_keyframe));
    const shift = Math.hypot(correction.T_correction[3], correction.T_correction[7], correction.T_correction[11]);
    this.hud.toast(`loop closed (${correction.loops}): map corrected by ${(100 * shift).toFixed(1)} cm here`, "ok", 5000);
  }

  #serverError(error) {
    this.seen.errors.push(error);
    if (this.seen.errors.length > 200) this.seen.errors.shift();
    if (error.seq !== undefined) this.streamer?.dropImagesUpTo(error.seq);
    if (error.name === "unreachable_target" && error.nearest && this.tapCommands.has(error.command_id)) {
      this.tapCommands.delete(error.command_id);
      this.hud.toast("That point cannot be reached: flying to the nearest reachable point instead.", "warn");
      this.pilot.goto(error.nearest);
      return;
    }
    const text = `${error.name} (${error.code}): ${error.message}`;
    if (error.fatal) this.hud.showBanner(text, "error", 10000);
    else this.hud.toast(text, "error", 6000);
  }

  // ---- pilot ------------------------------------------------------------------------------------

  #tapAR(pixel, seq) {
    const id = this.pilot.gotoPixel(pixel.map((v) => Math.round(v * 10) / 10), seq);
    if (id !== null) this.tapCommands.add(id);
    this.hud.toast(id === null ? "not connected: tap ignored" : `fly to pixel ${pixel.map(Math.round).join(", ")}`, id === null ? "warn" : "info", 2000);
  }

  #tapMap(picked) {
    const target = MapView.targetFor(picked);
    const id = this.pilot.goto(target);
    if (id !== null) this.tapCommands.add(id);
    this.hud.toast(id === null ? "not connected: tap ignored" : `fly to ${target.map((v) => v.toFixed(2)).join(", ")} m`, id === null ? "warn" : "info", 2000);
  }

  #wireControls() {
    $("#btn-stream").addEventListener("click", () => (this.streamer?.running ? this.stopStreaming() : this.resume()));
    $("#btn-takeoff").addEventListener("click", () => this.pilot.takeoff());
    $("#btn-hold").addEventListener("click", () => this.pilot.hold());
    $("#btn-land").addEventListener("click", () => this.pilot.land());
    $("#btn-download").addEventListener("click", () => this.downloadMap());
    $("#btn-menu").addEventListener("click", () => this.#openDialog());
    $("#btn-fit").addEventListener("click", () => this.map.fit());
    $("#btn-colour").addEventListener("click", (e) => {
      const mode = this.map.colourMode === "height" ? "rgb" : "height";
      this.map.setColourMode(mode);
      e.target.textContent = mode === "height" ? "Height" : "Colour";
    });
    $("#btn-occlusion").addEventListener("click", () => this.setOcclusion(!this.ar.occlusion.enabled));
    for (const button of document.querySelectorAll("[data-view]")) {
      button.addEventListener("click", () => this.setView(button.dataset.view));
    }
    this.pilot.addEventListener("refused", (e) => this.hud.toast(`command refused here: ${e.detail.message}`, "error"));
    this.setView(document.body.className.replace("layout-", "") || "split");
  }

  /** Real surfaces hide the drone in AR (occlusion.js), or the drone is drawn on top. */
  setOcclusion(on) {
    this.ar.occlusion.enabled = on;
    this.ar.dirty = true;
    $("#btn-occlusion").setAttribute("aria-pressed", String(on));
  }

  setView(view) {
    document.body.classList.remove("layout-ar", "layout-split", "layout-map", "layout-fpv");
    document.body.classList.add(`layout-${view}`);
    for (const button of document.querySelectorAll("[data-view]")) {
      button.setAttribute("aria-pressed", String(button.dataset.view === view));
    }
  }

  async downloadMap() {
    try {
      const { blob, filename } = await this.client.downloadMap();
      const url = URL.createObjectURL(blob);
      const a = document.createElement("a");
      a.href = url;
      a.download = filename;
      document.body.append(a);
      a.click();
      a.remove();
      setTimeout(() => URL.revokeObjectURL(url), 10000);
      this.hud.toast(`map saved as ${filename} (${(blob.size / 1e6).toFixed(1)} MB)`, "ok");
    } catch (exc) {
      this.hud.toast(exc.message, "error", 6000);
    }
  }

  #renderLoop() {
    let lastHud = 0;
    const frame = (now) => {
      const view = document.body.classList;
      const fpv = view.contains("layout-fpv");
      if (!view.contains("layout-map") && !fpv && !this.source?.session) this.ar.tick(now);
      if (!view.contains("layout-ar") && !fpv) this.map.tick(now);
      if (fpv) this.fpv.tick(now);
      this.flights.tick(now);
      this.course.tick(now);
      // The mesh is fetched only while a view draws it: FPV, or live AR's occlusion when the XR
      // frames have had no depth for a while (not for one frame without it).
      const noDepth = this.ar.occlusion.depthMissingSince;
      this.mapMesh.wanted = fpv || (this.ar.occlusion.enabled && this.source?.kind === "live" &&
        noDepth !== null && now - noDepth > MESH_AFTER_NO_DEPTH_MS);
      this.mapMesh.poll(now);
      if (now - lastHud > 250) {
        lastHud = now;
        const waits = this.hud.rates({ latencyMs: this.client.latencyMs, clientSkipped: this.streamer?.skipped ?? 0,
          serverDropped: this.seen.serverDropped, askedFps: this.streamer?.running ? this.streamer.fps : 0,
          load: this.load.summary(now) });
        this.budget.streamBehind = waits !== null; // then the views draw less often
      }
      this.budget.update(now);
      requestAnimationFrame(frame);
    };
    requestAnimationFrame(frame);
  }

  // ---- setup dialog -------------------------------------------------------------------------------

  #dialogChoice() {
    const form = $("#setup-form");
    const data = new FormData(form);
    return { mode: data.get("mode"), fps: Number(data.get("fps")), fresh: data.get("session") === "new",
      room: data.get("session") === "room", loops: data.get("loops") === "on",
      files: $("#folder-input").files, recording: $("#recording-input").files?.[0] ?? null };
  }

  #openDialog() {
    const session = this.client.session;
    $("#session-status").textContent = session ? `session ${session.id}` : "a new session starts if there is none";
    $("#setup-error").hidden = true;
    $("#setup").showModal();
  }

  async #setupDialog() {
    const dialog = $("#setup");
    const liveOption = $("#live-option");
    const support = await liveSupport();
    $("#live-status").textContent = support.reason;
    if (!support.supported) {
      liveOption.classList.add("unsupported");
      liveOption.querySelector("input").disabled = true;
    }
    this.liveSupport = support;
    // First visit: say what Start will do. A phone with WebXR AR starts in the live mode.
    const chosen = new URLSearchParams(window.location.search).get("mode");
    if (support.supported && !chosen) document.querySelector('input[name="mode"][value="live"]').checked = true;
    if (!this.client.session) {
      this.hud.toast(support.supported ? "Press Start for live AR (Setup: replay instead)."
        : `Live AR is not available here: ${support.reason} Press Start to replay the demo.`, "info", 9000);
    }
    $("#folder-input").addEventListener("change", () => {
      document.querySelector('input[name="mode"][value="folder"]').checked = true;
    });
    $("#recording-input").addEventListener("change", () => {
      document.querySelector('input[name="mode"][value="iphone"]').checked = true;
      const file = $("#recording-input").files?.[0];
      $("#recording-status").textContent = file ? `${file.name}: Start uploads it` : "";
    });
    dialog.addEventListener("close", async () => {
      if (dialog.returnValue === "end") {
        this.stopStreaming();
        this.client.bye("ended by the user");
        this.client.forget();
        this.streamer = null;
        this.#resetViews();
        this.hud.toast("session ended", "info");
      } else if (dialog.returnValue === "start") {
        const choice = this.#dialogChoice();
        if (choice.mode === "folder" && !choice.files?.length) {
          this.hud.toast("pick a folder first", "warn");
          return;
        }
        if (choice.mode === "iphone" && !choice.recording) {
          this.hud.toast("pick a recording first (.r3d, or a Stray Scanner export zipped)", "warn");
          return;
        }
        try {
          await this.start(choice);
        } catch {
          /* shown in the banner */
        }
      }
    });
  }

  /** What the page saw, as plain data (tests, debugging). */
  snapshot() {
    const rect = this.ar.stage.getBoundingClientRect();
    return {
      connection: this.client.state,
      session: this.client.session?.id ?? null,
      streaming: this.streamer?.running ?? false,
      sent: this.client.counts.sent,
      counts: { ...this.client.counts },
      statusLog: this.client.statusLog.map(({ state, message }) => ({ state, message })),
      skipped: this.streamer?.skipped ?? 0,
      unavailable: { ...(this.streamer?.unavailable ?? {}) },
      heldBack: this.streamer?.heldBack ?? false,
      heldBackMs: this.streamer?.heldBackMs ?? 0,
      inFlight: this.client.inFlight.size,
      latencyMs: this.client.latencyMs,
      hello: this.hello ?? null,
      recordingStatus: $("#recording-status")?.textContent ?? "",
      ...this.seen,
      ar: { ...this.ar.lastDraw, stage: { left: rect.left, top: rect.top, width: rect.width, height: rect.height },
        intrinsics: this.ar.intrinsics, colourSize: this.ar.colourSize, shownSeq: this.ar.frame?.seq ?? null },
      occlusion: { enabled: this.ar.occlusion.enabled, source: this.ar.lastDraw.occlusion ?? "none",
        depthSeq: this.ar.occlusion.depth?.seq ?? null, depthFailures: this.frameDepths.failures },
      fpv: { ...this.fpv.lastDraw }, mesh: this.mapMesh.summary(), budget: this.budget.summary(),
      load: this.load.summary(), waitsFor: this.hud.waits.shown ? this.hud.waits.last?.name ?? null : null,
      trail: { points: this.map.trajectory.count, last: this.map.trajectory.count
        ? Array.from(this.map.trajectory.array.subarray(3 * this.map.trajectory.count - 3, 3 * this.map.trajectory.count)) : null },
      commands: this.pilot.log.map(({ id, name, fields }) => ({ id, name, fields })),
      liveSupport: this.liveSupport ?? null,
      viewer: this.client.viewer === true,
      ...this.flights.snapshot(),
      course: this.course.snapshot(),
    };
  }
}

const app = new App();
window.dronesim = app;
app.ready = app.init().catch((exc) => {
  console.error(exc);
  document.body.insertAdjacentHTML("afterbegin", `<p class="error" style="padding:12px">The page could not start: ${exc.message}</p>`);
});
