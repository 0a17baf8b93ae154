// "Invite a phone" (the Flights dialog's Share part): the owner of a live session asks the
// server for a join token (POST /api/sessions/{id}/invites) and shows the link another phone
// opens to join the session's shared room, #join=<id>&token=<join token>, with its QR code.
// The token stays in the link's fragment, which a browser never sends to a server: the code is
// made here (qr_code.js), not by the server as the phone-link card's is.

import { inviteToRoom, startRace } from "../network/session_rest.js";
import { qrSvg } from "./qr_code.js";

const $ = (selector) => document.querySelector(selector);
const LOOPBACK = new Set(["127.0.0.1", "localhost", "[::1]"]);

/** Where a phone opens the page: this page's origin, unless that is loopback, which no phone
 * reaches: then the server's LAN URL (the phone-link card's), when it has one. */
async function linkOrigin() {
  if (!LOOPBACK.has(window.location.hostname)) return window.location.origin;
  try {
    const answer = await fetch("/api/phone-link");
    const urls = answer.ok ? (await answer.json()).urls : [];
    if (urls.length) return new URL(urls[0]).origin;
  } catch {
    /* an older server: this page's origin */
  }
  return window.location.origin;
}

export class Invite {
  /** @param {{client: import("../network/connection.js").SocketClient, hud: import("./hud.js").Hud}} parts */
  constructor({ client, hud }) {
    this.client = client;
    this.hud = hud;
    this.link = null;
    this.button = $("#btn-invite");
    this.button.addEventListener("click", () => this.invite());
    this.raceButton = $("#btn-race");
    this.raceButton.addEventListener("click", () => this.race());
    this.race_ = null; // the latest race this page started ({race, gates, ...})
    // Only a room's owner invites and starts races: a joined phone, or a viewer, has no button.
    const update = () => {
      this.button.hidden = this.raceButton.hidden = Boolean(client.viewer || client.joined);
    };
    client.addEventListener("status", update);
    update();
  }

  /** Start a race in this session's room (an easy course, 3 s of countdown). */
  async race() {
    try {
      const session = this.client.session;
      if (!session?.id || !session.token) throw new Error("start a session first");
      this.race_ = await startRace(this.client.baseUrl, session);
      this.hud.toast(`race ${this.race_.race}: ${this.race_.gates} gates, go in ${this.race_.starts_in_s} s`, "info", 4000);
    } catch (exc) {
      this.hud.toast(`no race: ${exc.message}`, "error", 6000);
    }
  }

  /** Ask for a join token and show the link and its QR code. */
  async invite() {
    const card = $("#invite");
    try {
      const session = this.client.session;
      if (!session?.id || !session.token) throw new Error("start a session first: a phone joins its room");
      if (this.client.joined) throw new Error("this phone joined another's room: only the room's owner invites");
      const { join, join_token: token } = await inviteToRoom(this.client.baseUrl, session);
      const link = `${await linkOrigin()}/#join=${encodeURIComponent(join)}&token=${encodeURIComponent(token)}`;
      const qr = $("#invite-qr");
      qr.src = `data:image/svg+xml;charset=utf-8,${encodeURIComponent(qrSvg(link))}`;
      qr.alt = `QR code of ${link}`;
      $("#invite-link").value = link;
      card.hidden = false;
      // The SVG decodes after src is set: the link counts as shown once its code is drawn,
      // so nobody (a test's screenshot included) reads a blank square.
      await qr.decode().catch(() => {});
      this.link = link;
      navigator.clipboard?.writeText(link).catch(() => {});
    } catch (exc) {
      card.hidden = true;
      this.hud.toast(`no invitation: ${exc.message}`, "error", 6000);
    }
  }
}
