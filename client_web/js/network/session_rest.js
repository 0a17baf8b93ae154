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
 * session in the room that session left; `loopClosure` true or false asks it to close loops or
 * not (null: the server's setting).
 */
export function createSession(baseUrl, { token = null, room = undefined, loopClosure = null } = {}) {
  const body = room === undefined ? { loop_closure: loopClosure } : { room, loop_closure: loopClosure };
  return request(baseUrl, "POST", "/api/sessions", token, body);
}

/** A session's status ({closed, ...}); throws when the server does not know it. */
export function sessionStatus(baseUrl, { id, token }) {
  return request(baseUrl, "GET", `/api/sessions/${id}`, token);
}

/** A session's file (map.ply, mesh.ply, trajectory.tum) -> {blob, filename}. */
export async function downloadFile(baseUrl, { id, token }, name) {
  if (!id) throw new Error("no session yet: start streaming first");
  const response = await fetch(`${baseUrl}/api/sessions/${id}/${name}`, {
    headers: { Authorization: `Bearer ${token}` },
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
