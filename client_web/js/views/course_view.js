// Courses on the page: the Course button and its panel (difficulty, seed, autopilot demo,
// start and stop, the session's best runs), the gates drawn as rings in the AR view and on the
// map, and a HUD line with the run's time, gates k/n, score, damage and crashes. Everything the
// server says about a course comes in `course` messages and drone events (shared/PROTOCOL.md,
// "Courses"); gates are in the world frame like every other position.

import * as THREE from "three";

const Z_AXIS = new THREE.Vector3(0, 0, 1);
const TUBE_M = { ar: 0.025, map: 0.045 }; // the ring's tube radius, drawn outside the gate's radius
export const GATE_COLOURS = Object.freeze({
  next: 0x00ff66, // the one to fly through now: bright green
  pending: 0x38c8ff, // later ones: light blue
  passed: 0x2f7d4a, // dim green
  missed: 0xff3b30, // red
});
const DIFFICULTIES = ["easy", "medium", "hard"];
const EVENT_TEXT = { gate_passed: "ok", gate_missed: "warn", course_finished: "ok" };

/** One gate's look: a ring (torus) in the plane normal to the way through, a cone pointing that
 * way at its centre (shown for the next gate), in the gate's own frame (z = the normal). */
export function gateMesh(radius, tube) {
  const group = new THREE.Group();
  group.matrixAutoUpdate = false;
  const material = new THREE.MeshBasicMaterial({ color: GATE_COLOURS.pending, transparent: true, opacity: 0.95 });
  const ring = new THREE.Mesh(new THREE.TorusGeometry(radius + tube, tube, 10, 48), material);
  const arrowMaterial = new THREE.MeshBasicMaterial({ color: GATE_COLOURS.next, transparent: true, opacity: 0.8 });
  const arrow = new THREE.Mesh(new THREE.ConeGeometry(0.05, 0.14, 16), arrowMaterial);
  arrow.rotation.x = Math.PI / 2; // cone axis (y) -> z, the way through
  group.add(ring, arrow);
  group.userData = { ring, arrow, material, arrowMaterial };
  return group;
}

export class CourseView {
  /**
   * @param {{client: import("../network/connection.js").SessionClient,
   *   state: import("../session/state.js").SessionState, ar: import("./ar_view.js").ARView,
   *   map: import("./map_view.js").MapView, hud: import("../ui/hud.js").Hud}} parts
   *   client: sends the course commands; state: what the server says of the course and the drone
   */
  constructor({ client, state, ar, map, hud }) {
    this.client = client;
    this.state = state;
    this.ar = ar;
    this.map = map;
    this.hud = hud;
    this.course = null; // the latest course message
    this.receivedAt = 0; // performance.now() when it came
    this.damage = 0;
    this.crashed = false;
    this.best = [];
    this.log = []; // course events seen: {event, message}
    this.arGroup = new THREE.Group();
    this.mapGroup = new THREE.Group();
    this.ar.world.add(this.arGroup);
    this.map.scene.add(this.mapGroup);
    this.#buildUi();
    this.#listen();
  }

  // ---- the server's side ----------------------------------------------------------------------

  #listen() {
    this.state.addEventListener("course", ({ detail }) => this.setCourse(detail));
    this.state.addEventListener("reset", () => this.clear());
    this.state.addEventListener("drone", ({ detail }) => {
      const damage = detail.damage ?? 0;
      const crashed = detail.mode === "crashed";
      if (damage !== this.damage || crashed !== this.crashed) {
        this.damage = damage;
        this.crashed = crashed;
        this.#updateHud();
      }
    });
    this.state.addEventListener("drone_event", ({ detail: e }) => {
      if (!(e.event in EVENT_TEXT)) return;
      this.log.push({ event: e.event, message: e.message });
      if (this.log.length > 100) this.log.shift();
      if (e.event === "course_finished") this.hud.showBanner(e.message, "ok", 6000);
      else this.hud.toast(e.message, EVENT_TEXT[e.event], 2500);
    });
  }

  /** A course message: redraw the rings when the gates change, recolour them, update the HUD. */
  setCourse(course) {
    const fresh = !this.course || this.course.course_id !== course.course_id;
    this.course = course;
    this.receivedAt = performance.now();
    if (fresh) this.#buildGates(course);
    this.#colourGates(course);
    this.#updateHud();
    this.#updatePanel();
    if (fresh) this.hud.toast(`course ${course.difficulty}: ${this.gateCount} gates${course.autopilot ? ", autopilot" : ""}`, "info", 3000);
    if (course.state === "finished") this.refreshBest();
  }

  get gateCount() {
    return this.course ? this.course.gates.length / 7 : 0;
  }

  #buildGates(course) {
    for (const group of [this.arGroup, this.mapGroup]) {
      for (const child of [...group.children]) {
        group.remove(child);
        child.traverse((o) => o.geometry?.dispose());
      }
    }
    const g = course.gates;
    for (let i = 0; i + 6 < g.length; i += 7) {
      const centre = new THREE.Vector3(g[i], g[i + 1], g[i + 2]);
      const normal = new THREE.Vector3(g[i + 3], g[i + 4], g[i + 5]).normalize();
      const pose = new THREE.Matrix4().compose(centre, new THREE.Quaternion().setFromUnitVectors(Z_AXIS, normal),
        new THREE.Vector3(1, 1, 1));
      for (const [group, tube] of [[this.arGroup, TUBE_M.ar], [this.mapGroup, TUBE_M.map]]) {
        const gate = gateMesh(g[i + 6], tube);
        gate.matrix.copy(pose);
        gate.name = `gate-${i / 7}`;
        group.add(gate);
      }
    }
  }

  #colourGates(course) {
    const running = course.state === "running";
    course.gate_states.forEach((state, k) => {
      const look = state === "pending" && k === course.next_gate && running ? "next" : state;
      for (const group of [this.arGroup, this.mapGroup]) {
        const gate = group.children[k];
        if (!gate) continue;
        gate.userData.material.color.setHex(GATE_COLOURS[look]);
        gate.userData.material.opacity = look === "passed" ? 0.45 : 0.95;
        gate.userData.arrow.visible = look === "next";
      }
    });
    const visible = course.state !== "stopped";
    this.arGroup.visible = this.mapGroup.visible = visible;
    this.ar.dirty = true;
    this.map.dirty = true;
  }

  /** Forget the course (a new session). */
  clear() {
    this.course = null;
    this.damage = 0;
    this.crashed = false;
    this.arGroup.visible = this.mapGroup.visible = false;
    this.#updateHud();
  }

  // ---- commands ---------------------------------------------------------------------------------

  /** Ask for a course: {difficulty, seed, autopilot}; the command's id, or null. */
  start({ difficulty = "medium", seed = null, autopilot = false } = {}) {
    const fields = { difficulty, autopilot: Boolean(autopilot) };
    if (seed !== null && seed !== "" && Number.isFinite(Number(seed))) fields.seed = Math.max(0, Math.round(Number(seed)));
    return this.#send("course_start", fields);
  }

  stop() {
    return this.#send("course_stop");
  }

  #send(name, fields = {}) {
    try {
      const id = this.client.command(name, fields);
      if (id === null) this.hud.toast("not connected: start streaming first", "warn");
      return id;
    } catch (exc) {
      this.hud.toast(`command refused here: ${exc.message}`, "error");
      return null;
    }
  }

  /** The session's best runs (GET /api/sessions/{id}/course/best), shown in the panel. */
  async refreshBest() {
    try {
      const { blob } = await this.client.download("course/best");
      this.best = JSON.parse(await blob.text()).results ?? [];
    } catch (exc) {
      console.info("no best list yet", exc.message);
    }
    this.#updatePanel();
  }

  // ---- the page ---------------------------------------------------------------------------------

  #buildUi() {
    const button = document.createElement("button");
    button.id = "btn-course";
    button.textContent = "Course";
    button.title = "fly a course of gates through the mapped room";
    button.addEventListener("click", () => this.openPanel());
    document.querySelector("#controls .buttons.flight")?.append(button);

    const row = document.createElement("div");
    row.className = "hud-row course-hud";
    row.hidden = true;
    row.innerHTML = `<span class="chip" data-course="time" title="course time / par time">time —</span>
      <span class="chip" data-course="gates" title="gates passed of all">gates —</span>
      <span class="chip" data-course="score" title="score so far">score —</span>
      <span class="chip" data-course="damage" title="bump damage, crashes">dmg 0</span>`;
    document.querySelector("#hud")?.append(row);
    this.hudRow = row;
    this.chips = Object.fromEntries([...row.querySelectorAll("[data-course]")].map((el) => [el.dataset.course, el]));

    const dialog = document.createElement("dialog");
    dialog.id = "course-dialog";
    dialog.innerHTML = `<form method="dialog">
      <h2>Course</h2>
      <fieldset><legend>Difficulty</legend>
        ${DIFFICULTIES.map((d) => `<label class="option"><input type="radio" name="difficulty" value="${d}"${d === "easy" ? " checked" : ""}>
          <span><b>${d}</b></span></label>`).join("")}
      </fieldset>
      <label class="inline">Seed <input type="number" name="seed" min="0" step="1" placeholder="random" inputmode="numeric"></label>
      <label class="inline"><input type="checkbox" name="autopilot"> Autopilot demo (the planner flies it)</label>
      <p class="course-status" id="course-status"></p>
      <ol class="course-best" id="course-best"></ol>
      <div class="dialog-buttons">
        <button value="cancel" formnovalidate>Close</button>
        <button value="stop" id="btn-course-stop" formnovalidate>Stop course</button>
        <button value="start" class="primary" id="btn-course-start">Start course</button>
      </div>
    </form>`;
    document.body.append(dialog);
    this.dialog = dialog;
    dialog.addEventListener("close", () => {
      if (dialog.returnValue === "start") this.start(this.panelChoice());
      else if (dialog.returnValue === "stop") this.stop();
    });
  }

  panelChoice() {
    const data = new FormData(this.dialog.querySelector("form"));
    return { difficulty: data.get("difficulty"), seed: data.get("seed") || null, autopilot: data.get("autopilot") === "on" };
  }

  openPanel() {
    this.#updatePanel();
    this.dialog.showModal();
    if (this.client.session) this.refreshBest();
  }

  #updatePanel() {
    if (!this.dialog) return;
    const c = this.course;
    this.dialog.querySelector("#course-status").textContent = c
      ? `course ${c.course_id} (${c.difficulty}, seed ${c.seed}): ${c.state}, ${c.gate_states.filter((s) => s === "passed").length}/${this.gateCount} gates, score ${c.score}`
      : "no course yet";
    this.dialog.querySelector("#btn-course-stop").disabled = c?.state !== "running";
    const list = this.dialog.querySelector("#course-best");
    list.replaceChildren(...this.best.map((r) => {
      const li = document.createElement("li");
      li.textContent = `${r.score} pts: ${r.passed}/${r.gates} gates in ${r.time_s.toFixed(1)} s (${r.difficulty}, seed ${r.seed}${r.autopilot ? ", autopilot" : ""})`;
      return li;
    }));
  }

  /** The course's time: the server's, run on locally between its messages while running. */
  elapsed(now = performance.now()) {
    const c = this.course;
    if (!c) return 0;
    return c.elapsed_s + (c.state === "running" ? (now - this.receivedAt) / 1000 : 0);
  }

  #updateHud() {
    const c = this.course;
    this.hudRow.hidden = !c;
    if (!c) return;
    const passed = c.gate_states.filter((s) => s === "passed").length;
    const state = { running: "flying", finished: "ok", stopped: "none" }[c.state];
    this.#chip("time", `time ${this.elapsed().toFixed(1)} / ${c.par_s.toFixed(1)} s`, state);
    this.#chip("gates", `gates ${passed}/${this.gateCount}`, c.gate_states.includes("missed") ? "warn" : state);
    this.#chip("score", `score ${c.score}${c.rank ? ` #${c.rank}` : ""}`, state);
    const bumps = c.bumps ? `, ${c.bumps} bump${c.bumps > 1 ? "s" : ""}` : "";
    const crashes = c.crashes ? `, ${c.crashes} crash${c.crashes > 1 ? "es" : ""}` : "";
    this.#chip("damage", this.crashed ? "CRASHED" : `dmg ${Math.round(this.damage)}${bumps}${crashes}`,
      this.crashed ? "bad" : this.damage > 0 || c.bumps || c.crashes ? "warn" : "none");
  }

  #chip(name, text, state) {
    const el = this.chips[name];
    if (el.textContent !== text) el.textContent = text;
    el.dataset.state = state;
  }

  /** Call every animation frame: the running clock in the HUD. */
  tick(now) {
    if (this.course?.state === "running" && now - (this.lastTick ?? 0) > 100) {
      this.lastTick = now;
      this.#chip("time", `time ${this.elapsed(now).toFixed(1)} / ${this.course.par_s.toFixed(1)} s`, "flying");
    }
  }

  /** What the page shows of the course, as plain data (tests, debugging). */
  snapshot() {
    const c = this.course;
    const rings = (group) => group.children.map((g) => ({
      colour: g.userData.material.color.getHex(), position: new THREE.Vector3().setFromMatrixPosition(g.matrix).toArray(),
    }));
    return {
      course: c ? { ...c } : null,
      arRings: this.arGroup.visible ? rings(this.arGroup) : [],
      mapRings: this.mapGroup.visible ? rings(this.mapGroup) : [],
      hud: this.hudRow.hidden ? null : this.hudRow.textContent.replace(/\s+/g, " ").trim(),
      damage: this.damage,
      crashed: this.crashed,
      best: this.best,
      log: [...this.log],
    };
  }
}
