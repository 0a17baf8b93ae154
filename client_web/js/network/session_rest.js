// The session's REST calls (shared/PROTOCOL.md, "Sessions over REST"): create a session, ask
// whether one is still open, download its files. Errors carry the server's own message
// ({"error": {"code", "message"}}) and the HTTP status.

/** One JSON request; throws an Error (with .status) that says what the server answered. */
async function request(baseUrl, method, path, token, json = undefined) {
  const headers = token ? { Authorization: `Bearer ${token}` } : {};
  if (json !== undefined) headers["Content-Type"] = "application/json";
  const body = json === undefined ? undefined : JSON.stringify(json);
  const response = await fetch(`${baseUrl}${path}`, { method, headers, body });
  let answer = null;
  try {
    answer = await response.json();
  } catch {
    /* no body */
  }
  if (!response.ok) {
    const why = answer?.error?.message ?? answer?.detail ?? response.statusText;
    const error = new Error(`${method} ${path}: HTTP ${response.status} ${why}`);
    error.status = response.status;
    throw error;
  }
  return answer;
}

/**
 * A new session: {id, token, ...}. With `room` (an ended session's id, and its `token`), a new
 * session in the room that session left; with `join` (a live session's id, and a join token of
 * its invitation as `token`), a session of this phone's own in that session's shared room;
 * `loopClosure` true or false asks it to close loops or not (null: the server's setting; a
 * joined session keeps the room's keyframes, so it sends none).
 */
export function createSession(baseUrl, { token = null, room = undefined, join = undefined, loopClosure = null } = {}) {
  let body = { loop_closure: loopClosure };
  if (room !== undefined) body = { room, loop_closure: loopClosure };
  if (join !== undefined) body = { join };
  return request(baseUrl, "POST", "/api/sessions", token, body);
}

/** An invitation into a live session's shared room: {join_token, join}. Only the session's
 * own token invites (a joined phone's is refused: 409 room_unavailable). */
export function inviteToRoom(baseUrl, { id, token }) {
  return request(baseUrl, "POST", `/api/sessions/${encodeURIComponent(id)}/invites`, token);
}

/** The invitation of a page's fragment (#join=<owner id>&token=<join token>), or null: a link
 * another phone opened (the fragment never travels to a server). */
export function joinLink(hash = window.location.hash) {
  const params = new URLSearchParams(hash.replace(/^#/, ""));
  const id = params.get("join");
  const token = params.get("token");
  return id && token ? { id, token } : null;
}

/** A race in a live session's shared room (its own token): {race, gates, difficulty, seed,
 * starts_in_s}; every live phone of the room flies the course after the countdown. */
export function startRace(baseUrl, { id, token }, { difficulty = "easy", countdownS = 3 } = {}) {
  return request(baseUrl, "POST", `/api/sessions/${encodeURIComponent(id)}/race`, token,
    { difficulty, countdown_s: countdownS });
}

/** A session's status ({closed, ...}); throws when the server does not know it. */
export function sessionStatus(baseUrl, { id, token }) {
  return request(baseUrl, "GET", `/api/sessions/${id}`, token);
}

/** A session's file (map.ply, mesh.ply, trajectory.tum) -> {blob, filename}; `signal` (an
 * AbortSignal) may give it up. */
export async function downloadFile(baseUrl, { id, token }, name, signal = undefined) {
  if (!id) throw new Error("no session yet: start streaming first");
  const response = await fetch(`${baseUrl}/api/sessions/${id}/${name}`, {
    headers: { Authorization: `Bearer ${token}` }, signal,
  });
  if (!response.ok) {
    let why = response.statusText;
    try {
      why = (await response.json())?.error?.message ?? why;
    } catch {
      /* not json */
    }
    throw new Error(`${name} download failed: HTTP ${response.status} ${why}`);
  }
  return { blob: await response.blob(), filename: `${id}-${name}` };
}
