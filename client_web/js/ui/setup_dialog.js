// The Setup dialog: the capture mode (demo replays, a TUM folder, an iPhone recording, live AR
// where this browser offers it), the session (continue, new, a saved room), loop closure and
// the frame rate; Start and End session. Also the upload of an iPhone recording, whose progress
// shows in the dialog.

import { liveSupport } from "../capture/sources/live.js";
import { ReplaySequence } from "../capture/sources/replay.js";

const $ = (selector) => document.querySelector(selector);
const modeRadio = (mode) => document.querySelector(`input[name="mode"][value="${CSS.escape(mode)}"]`);

export class SetupDialog {
  /**
   * @param {import("../session/control.js").SessionControl} control starts and ends the session
   * @param {import("./hud.js").Hud} hud
   */
  constructor(control, hud) {
    this.control = control;
    this.hud = hud;
    this.dialog = $("#setup");
    this.support = null; // liveSupport(): {supported, reason}, once checked
    $("#btn-menu").addEventListener("click", () => this.open());
    $("#folder-input").addEventListener("change", () => (modeRadio("folder").checked = true));
    $("#recording-input").addEventListener("change", () => {
      modeRadio("iphone").checked = true;
      const file = $("#recording-input").files?.[0];
      $("#recording-status").textContent = file ? `${file.name}: Start uploads it` : "";
    });
    this.dialog.addEventListener("close", () => this.#closed(this.dialog.returnValue));
    control.addEventListener("tap-needed", () => (modeRadio("live").checked = true));
    control.addEventListener("failed", ({ detail }) => {
      if (detail.mode === "live") $("#live-status").textContent = detail.error.message; // stays in Setup, too
    });
  }

  /** Preselect a capture mode (?mode=demo, demo-small, folder, live...) unless it is disabled. */
  preselect(mode) {
    const radio = mode && modeRadio(mode);
    if (radio && !radio.disabled) radio.checked = true;
  }

  /** Whether this browser offers live AR: said in the dialog; a phone with it starts there. */
  async checkLive({ chosen = null, hasSession = false } = {}) {
    const support = await liveSupport();
    $("#live-status").textContent = support.reason;
    if (!support.supported) {
      $("#live-option").classList.add("unsupported");
      modeRadio("live").disabled = true;
    }
    this.support = support;
    // First visit: say what Start will do. A phone with WebXR AR starts in the live mode.
    if (support.supported && !chosen) modeRadio("live").checked = true;
    if (!hasSession) {
      this.hud.toast(support.supported ? "Press Start for live AR (Setup: replay instead)."
        : `Live AR is not available here: ${support.reason} Press Start to replay the demo.`, "info", 9000);
    }
  }

  /** The options the dialog says, for SessionControl.start. */
  choice() {
    const data = new FormData($("#setup-form"));
    return { mode: data.get("mode"), fps: Number(data.get("fps")), fresh: data.get("session") === "new",
      room: data.get("session") === "room", loops: data.get("loops") === "on",
      files: $("#folder-input").files, recording: $("#recording-input").files?.[0] ?? null };
  }

  open() {
    const session = this.control.client.session;
    $("#session-status").textContent = session ? `session ${session.id}` : "a new session starts if there is none";
    $("#setup-error").hidden = true;
    this.dialog.showModal();
  }

  async #closed(action) {
    if (action === "end") {
      this.control.end();
    } else if (action === "start") {
      const choice = this.choice();
      if (choice.mode === "folder" && !choice.files?.length) {
        this.hud.toast("pick a folder first", "warn");
        return;
      }
      if (choice.mode === "iphone" && !choice.recording) {
        this.hud.toast("pick a recording first (.r3d, or a Stray Scanner export zipped)", "warn");
        return;
      }
      try {
        await this.control.start(choice);
      } catch {
        /* shown in the banner */
      }
    }
  }
}

/** Upload an iPhone recording for the server to convert, saying how far it got (in the dialog
 * and in toasts). -> the converted ReplaySequence. */
export async function uploadRecording(file, hud) {
  if (!file) throw new Error("pick a recording first (.r3d, or a Stray Scanner export zipped)");
  const status = $("#recording-status");
  const say = (text) => {
    status.textContent = text;
    hud.toast(text, "info", 3000);
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
    return sequence;
  } catch (exc) {
    status.textContent = exc.message;
    throw exc;
  }
}
