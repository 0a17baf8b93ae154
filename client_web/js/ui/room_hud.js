// The HUD's shared-room row: one chip per pilot in the room (this page's marked "you", or
// "watched" on a viewer link's page; a joined phone not placed yet "placing…", else its
// drone's mode), edged in the colour its drone wears; and, on a phone that joined a room, the
// hint to look at a mapped part of the room until a frame is recognised there (its poses are
// "lost", at the identity, until then: PROTOCOL.md, "A shared room").

import { pilotLabel } from "../session/room.js";
import { pilotColour } from "../views/room_pilots.js";

export const PLACE_HINT = "Move the phone over a part of the room that is already mapped";
const NAME_CHARS = 18; // a pilot's name (its hello's client_name) is cut beyond this

const hex = (colour) => `#${colour.toString(16).padStart(6, "0")}`;

export class RoomHud {
  /** @param {{client: import("../network/connection.js").SocketClient, root?: Document}} parts */
  constructor({ client, root = document }) {
    this.client = client;
    this.row = root.querySelector("#room-row");
    this.list = root.querySelector("#room-pilots");
    this.hint = root.querySelector("#place-hint");
    this.raceChip = root.querySelector("#room-race");
    this.hint.textContent = PLACE_HINT;
    this.room = null;
    this.placed = false; // this joined session has had a pose in the room
    this.hintShown = false; // the hint was shown for this session (the tests read it)
  }

  /** Follow the session state (session/state.js): room messages, poses, new sessions. */
  follow(state) {
    state.addEventListener("room", ({ detail: room }) => this.show(room));
    state.addEventListener("pose", ({ detail: pose }) => {
      if (pose.state !== "lost") this.placed = true;
      this.#hint();
    });
    state.addEventListener("status", () => this.#hint());
    state.addEventListener("reset", () => {
      this.placed = false;
      this.hintShown = false;
      this.#hint();
    });
  }

  /** The room's pilots (session/room.js), or null: the row hides. */
  show(room) {
    this.room = room;
    this.row.hidden = !room;
    if (!room) {
      this.list.replaceChildren();
      return;
    }
    const chips = room.pilots.map((pilot) => {
      const chip = this.list.children[pilot.index] ?? document.createElement("span");
      chip.className = "chip pilot";
      chip.dataset.pilot = String(pilot.index);
      chip.dataset.you = String(pilot.you);
      chip.dataset.state = pilot.you ? "flying" : "none";
      // Not placed: a joined phone not yet recognised in the room, or the owner's tracking lost.
      const lost = pilot.index > 0 ? "placing…" : "lost";
      const what = pilot.placed ? (pilot.mode === "none" ? "no drone" : pilot.mode) : lost;
      const you = this.client.viewer ? " (watched)" : " (you)"; // a viewer link watches that pilot
      const label = pilotLabel(pilot);
      const name = label.length > NAME_CHARS ? `${label.slice(0, NAME_CHARS - 1)}…` : label; // a chip, not a line
      // In a race: gates passed of the course's, the time, and the place once finished.
      const r = pilot.race;
      const standing = r && room.race.state !== "countdown" ?
        ` · ${r.passed}/${room.race.gates} · ${r.time.toFixed(1)} s${r.rank ? ` · #${r.rank}` : ""}` : "";
      const text = `${name}${pilot.you ? you : ""} · ${what}${standing}`;
      if (chip.textContent !== text) chip.textContent = text;
      chip.style.borderColor = pilot.you ? "" : hex(pilotColour(pilot.index));
      chip.title = `${label}: ${pilot.you ? "this phone's drone (magenta)" : "another phone in this room; its drone wears this colour"}`;
      return chip;
    });
    this.list.replaceChildren(...chips);
    this.#race(room.race);
    this.#hint();
  }

  /** The race's state in a chip of its own: the countdown, running, or the winner. */
  #race(race) {
    this.raceChip.hidden = !race;
    if (!race) return;
    const winner = this.room.pilots.find((p) => p.race?.rank === 1);
    const text = race.state === "countdown" ? `Race ${race.number} starts in ${Math.ceil(race.startsIn)} s` :
      race.state === "running" ? `Race ${race.number}: ${race.gates} gates` :
        `Race ${race.number} won by ${winner ? pilotLabel(winner) : "nobody"}`;
    if (this.raceChip.textContent !== text) this.raceChip.textContent = text;
  }

  /** The placing hint: a joined session whose socket is open and that has had no pose in the
   * room yet (once placed, a lost pose is the AR view's "tracking lost", as in any session). */
  #hint() {
    const show = Boolean(this.client.joined) && this.client.state === "open" && !this.placed;
    if (show) this.hintShown = true;
    this.hint.hidden = !show;
  }

  snapshot() {
    return {
      pilots: this.room?.pilots.map((p) => p.name) ?? [],
      you: this.room?.you ?? null,
      placed: this.room?.pilots.map((p) => p.placed) ?? [],
      modes: this.room?.pilots.map((p) => p.mode) ?? [],
      listed: [...this.list.children].map((chip) => chip.textContent),
      joined: this.client.joined ?? null,
      race: this.raceChip.hidden ? null : this.raceChip.textContent,
      placeHint: !this.hint.hidden,
      placeHintShown: this.hintShown,
    };
  }
}
