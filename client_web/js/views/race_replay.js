// A shared room's finished race replayed on the map: every pilot's recorded flights at once on
// the race's wall clock (GET /api/sessions/{id}/races/{n}/flights: a flight's rows happened at
// started_at + t - start_time_s, Unix seconds), each pilot's drone in its room colour
// (room_pilots.js, by its index in the race's pilots), the race's gates as the course view
// draws them (in grey: the pilots' colours stay theirs), and a HUD row with the race's clock,
// the pilots and Pause / Stop. The clock runs from a second before the start to a second after
// the last pilot finished, then the replay stops by itself. The flights are driven by
// flight_replay.js's FlightReplay, one FlightMarker per pilot.

import * as THREE from "three";
import { gateMesh } from "./course_view.js";
import { FlightMarker, FlightReplay, flightAt, poseAt } from "./flight_replay.js";
import { pilotColour } from "./room_pilots.js";

export const MARGIN_S = 1; // replayed before the start and after the end
const GATE_COLOUR = 0xdddddd; // neutral: no pilot's paint
const GATE_TUBE_M = 0.045; // as the course view's map rings
const LABEL_EVERY_MS = 100;
const Z_AXIS = new THREE.Vector3(0, 0, 1);

const hex = (colour) => `#${colour.toString(16).padStart(6, "0")}`;

/** A pilot's drone paint: its room colour, lit from within at half strength (room_pilots.js). */
function paintOf(index) {
  const colour = pilotColour(index);
  return { colour, emissive: new THREE.Color(colour).multiplyScalar(0.5).getHex() };
}

export class RaceReplay {
  /** @param {import("./map_view.js").MapView} mapView @param {{root?: Document, onStop?:
   * (ended: boolean) => void}} options onStop: the replay ended by itself (true) or was stopped */
  constructor(mapView, { root = document, onStop = null } = {}) {
    this.map = mapView;
    this.replay = new FlightReplay(mapView);
    this.onStop = onStop;
    this.race = null; // the race replayed (its record), or the last one
    this.pilots = []; // [{index, name, session, colour, flights, marker}]
    this.ended = false;
    this.gates = new THREE.Group();
    this.gates.name = "race-replay-gates";
    this.gates.visible = false;
    mapView.scene.add(this.gates);
    this.lastLabel = 0;
    this.#buildHud(root);
  }

  get playing() {
    return this.replay.playing;
  }

  /** Replay a race: `data` is GET .../races/{n}/flights's body, {race, pilots}. */
  play(data, speed = 1) {
    this.stop();
    const { race } = data;
    this.race = race;
    this.ended = false;
    this.pilots = data.pilots.map((p, index) => ({
      index, name: p.name, session: p.session, colour: pilotColour(index),
      flights: [...p.flights].sort((a, b) => a.started_at - b.started_at),
      marker: new FlightMarker(this.map, { paint: paintOf(index), name: `race-drone-${index}`, path: false }),
    }));
    this.#drawGates(race.gates);
    const from = race.started_at - MARGIN_S;
    const to = race.ended_at + MARGIN_S;
    this.#frame(from, to);
    const tracks = this.pilots.filter((p) => p.flights.length).map(({ marker, flights }) => ({ marker, flights }));
    this.replay.playTracks(tracks, { from, to, speed, onStop: (ended) => this.#stopped(ended) });
    this.#showHud();
  }

  pause(on = true) {
    this.replay.pause(on);
    this.#updateLabel();
  }

  /** Stop it now (a new replay, or the Stop button). */
  stop() {
    this.replay.stop(false);
  }

  #stopped(ended) {
    this.ended = ended;
    for (const p of this.pilots) p.marker.dispose();
    this.gates.visible = false;
    this.map.dirty = true;
    this.row.style.display = "none";
    this.row.hidden = true;
    this.onStop?.(ended);
  }

  /** Call every animation frame. */
  tick(now) {
    if (!this.replay.playing) return;
    this.replay.tick(now);
    if (this.replay.playing && now - this.lastLabel > LABEL_EVERY_MS) {
      this.lastLabel = now;
      this.#updateLabel();
    }
  }

  // ---- the scene ----------------------------------------------------------------------------

  #drawGates(g) {
    for (const child of [...this.gates.children]) {
      this.gates.remove(child);
      child.traverse((o) => o.geometry?.dispose());
    }
    for (let i = 0; i + 6 < g.length; i += 7) {
      const centre = new THREE.Vector3(g[i], g[i + 1], g[i + 2]);
      const normal = new THREE.Vector3(g[i + 3], g[i + 4], g[i + 5]).normalize();
      const gate = gateMesh(g[i + 6], GATE_TUBE_M);
      gate.matrix.compose(centre, new THREE.Quaternion().setFromUnitVectors(Z_AXIS, normal), new THREE.Vector3(1, 1, 1));
      gate.userData.material.color.setHex(GATE_COLOUR);
      gate.userData.material.opacity = 0.8;
      gate.userData.arrowMaterial.color.setHex(0xffffff);
      gate.userData.arrowMaterial.opacity = 0.5;
      gate.name = `race-gate-${i / 7}`;
      this.gates.add(gate);
    }
    this.gates.visible = true;
    this.map.dirty = true;
  }

  /** Look at the race from above and behind, as the map's Fit frames the map: its gates and
   * where its drones flew from `from` to `to`. */
  #frame(from, to) {
    const box = new THREE.Box3();
    for (const gate of this.gates.children) {
      const radius = gate.userData.ring.geometry.parameters.radius;
      box.expandByPoint(new THREE.Vector3().setFromMatrixPosition(gate.matrix).addScalar(radius));
      box.expandByPoint(new THREE.Vector3().setFromMatrixPosition(gate.matrix).addScalar(-radius));
    }
    for (const { flights } of this.pilots) {
      for (let wall = from; wall <= to; wall += 0.25) {
        const at = flightAt(flights, wall);
        const pose = at && poseAt(at.flight, at.elapsed);
        if (pose) box.expandByPoint(new THREE.Vector3(...pose.position));
      }
    }
    if (box.isEmpty()) return;
    const { camera, controls, up } = this.map;
    const centre = box.getCenter(new THREE.Vector3());
    const radius = Math.max(0.5, box.getSize(new THREE.Vector3()).length() / 2);
    const forward = new THREE.Vector3(0, 0, 1).addScaledVector(up, -up.z).normalize();
    camera.position.copy(centre).addScaledVector(forward, -radius * 1.1).addScaledVector(up, radius * 1.5);
    controls.target.copy(centre);
    controls.update();
    this.map.dirty = true;
  }

  // ---- the HUD row --------------------------------------------------------------------------

  #buildHud(root) {
    const row = root.createElement("div");
    row.className = "hud-row race-replay";
    row.id = "race-replay";
    row.setAttribute("aria-label", "a race replayed on the map");
    row.innerHTML = `<span class="chip" data-state="flying" data-race-replay="clock" role="status"></span>
      <span class="room-pilots" data-race-replay="pilots"></span>
      <button type="button" data-race-replay="pause">Pause</button>
      <button type="button" data-race-replay="stop">Stop</button>`;
    row.hidden = true;
    row.style.display = "none"; // .hud-row's display would show it hidden
    root.querySelector("#hud")?.append(row);
    this.row = row;
    this.clockChip = row.querySelector("[data-race-replay=clock]");
    this.pilotChips = row.querySelector("[data-race-replay=pilots]");
    this.pauseButton = row.querySelector("[data-race-replay=pause]");
    this.pauseButton.addEventListener("click", () => this.pause(!this.replay.paused));
    row.querySelector("[data-race-replay=stop]").addEventListener("click", () => this.stop());
  }

  #showHud() {
    this.pilotChips.replaceChildren(...this.pilots.map((p) => {
      const chip = document.createElement("span");
      chip.className = "chip pilot";
      chip.dataset.pilot = String(p.index);
      chip.style.borderColor = hex(p.colour);
      const result = this.race.pilots[p.index];
      chip.textContent = `${p.name || `pilot ${p.index + 1}`}${result?.rank ? ` #${result.rank}` : ""}${p.flights.length ? "" : " (no flight)"}`;
      return chip;
    }));
    this.row.hidden = false;
    this.row.style.display = "";
    this.#updateLabel();
  }

  /** The race's time (0 at its start), s, on the replay's clock. */
  get raceTime() {
    return this.race ? this.replay.clock - this.race.started_at : 0;
  }

  #updateLabel() {
    if (!this.race) return;
    const length = this.race.ended_at - this.race.started_at;
    const text = `race ${this.race.number} replay ${this.raceTime.toFixed(1)} / ${length.toFixed(1)} s${this.replay.paused ? " (paused)" : ""}`;
    if (this.clockChip.textContent !== text) this.clockChip.textContent = text;
    this.clockChip.dataset.state = this.replay.paused ? "paused" : "flying";
    this.pauseButton.textContent = this.replay.paused ? "Resume" : "Pause";
  }

  /** What is drawn, as plain data (the tests, debugging): the clock (Unix s), each pilot's
   * drone, and the map camera that draws them (its projection and view matrices, column-major
   * as three.js keeps them, and its canvas's place on the page). */
  snapshot() {
    const camera = this.map.camera;
    camera.updateMatrixWorld();
    const rect = this.map.renderer.domElement.getBoundingClientRect();
    return {
      playing: this.replay.playing,
      paused: this.replay.paused,
      ended: this.ended,
      race: this.race?.number ?? null,
      from: this.replay.from,
      to: this.replay.to,
      clock: this.replay.clock,
      raceTime: this.raceTime,
      label: this.row.hidden ? null : this.clockChip.textContent,
      gates: this.gates.visible ? this.gates.children.length : 0,
      drones: this.pilots.map((p) => ({
        index: p.index, name: p.name, colour: p.colour, visible: p.marker.drone.visible,
        flight: p.marker.flight?.id ?? null, position: p.marker.pose?.position ?? null,
      })),
      camera: { projection: camera.projectionMatrix.toArray(), view: camera.matrixWorldInverse.toArray(),
        canvas: { left: rect.left, top: rect.top, width: rect.width, height: rect.height } },
      pausedAt: this.replay.pausedAt, // performance.now(); the map's draws after it show the held drones
      drawnAt: this.map.lastRender, // the map's last draw (its animation frame's time)
    };
  }
}
