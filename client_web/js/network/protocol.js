// The wire protocol, read from the server's /protocol.json (shared/protocol.json, the one
// definition the Python server uses too): validate, encode and decode msgpack messages, build
// the client's messages. Mirrors server/protocol/; see shared/PROTOCOL.md.

import { decode as msgpackDecode, encode as msgpackEncode } from "@msgpack/msgpack";

export const CLIENT_TO_SERVER = "client_to_server";
export const SERVER_TO_CLIENT = "server_to_client";

/** A message breaks the protocol; `code` is an error name of protocol.json (e.g. invalid_field). */
export class ProtocolError extends Error {
  constructor(code, message) {
    super(`${code}: ${message}`);
    this.name = "ProtocolError";
    this.code = code;
    this.detail = message;
  }
}

const fail = (code, message) => {
  throw new ProtocolError(code, message);
};

const isPlainObject = (v) =>
  v !== null && typeof v === "object" && !Array.isArray(v) && !ArrayBuffer.isView(v) &&
  !(v instanceof ArrayBuffer);

// protocol.json type name -> does a JS value have it (before constraints).
const TYPE_CHECKS = {
  int: (v) => typeof v === "number" && Number.isInteger(v),
  float: (v) => typeof v === "number",
  str: (v) => typeof v === "string",
  bytes: (v) => v instanceof Uint8Array,
  bool: (v) => typeof v === "boolean",
  list: (v) => Array.isArray(v),
  map: (v) => isPlainObject(v),
};

const typeName = (v) =>
  v === null ? "null" : Array.isArray(v) ? "array" : v?.constructor?.name ?? typeof v;

// Length as Python's len(): code points for str, bytes for bytes, items for list and map.
function lengthOf(value, kind) {
  if (kind === "str") return [...value].length;
  if (kind === "bytes") return value.byteLength;
  if (kind === "map") return Object.keys(value).length;
  return value.length;
}

function checkValue(value, spec, where) {
  const kind = spec.type;
  if (!TYPE_CHECKS[kind](value)) fail("invalid_field", `${where} must be ${kind}, got ${typeName(value)}`);
  if (kind === "float" && !Number.isFinite(value)) fail("invalid_field", `${where} must be finite, got ${value}`);
  if ("min" in spec && value < spec.min) fail("invalid_field", `${where} = ${value} is below ${spec.min}`);
  if ("max" in spec && value > spec.max) fail("invalid_field", `${where} = ${value} is above ${spec.max}`);
  if ("enum" in spec && !spec.enum.includes(value)) {
    fail("invalid_field", `${where} = ${JSON.stringify(value)} is not one of ${spec.enum.join(", ")}`);
  }
  if (kind === "str" || kind === "bytes" || kind === "list" || kind === "map") {
    const n = lengthOf(value, kind);
    if ("length" in spec && n !== spec.length) fail("invalid_field", `${where} has length ${n}, need ${spec.length}`);
    if (n < (spec.min_length ?? 0) || n > (spec.max_length ?? Infinity)) {
      fail("invalid_field", `${where} has length ${n}, outside the limits`);
    }
  }
  if (kind === "list" && spec.items) value.forEach((item, i) => checkValue(item, spec.items, `${where}[${i}]`));
  if (kind === "map" && spec.values) {
    for (const [key, item] of Object.entries(value)) checkValue(item, spec.values, `${where}.${key}`);
  }
}

/** The protocol of one server: its version, limits, messages, errors and close codes. */
export class Protocol {
  /** @param {object} spec the parsed protocol.json */
  constructor(spec) {
    this.spec = spec;
    this.version = spec.version;
    this.limits = spec.limits;
    this.messages = spec.messages;
    this.errors = Object.fromEntries(spec.errors.map((e) => [e.name, e]));
    this.errorNames = Object.fromEntries(spec.errors.map((e) => [e.code, e.name]));
    this.closeCodes = Object.fromEntries(spec.close_codes.map((c) => [c.code, c]));
    this.semantic = {
      hello: (m) => this.#checkHello(m),
      command: (m) => this.#checkCommand(m),
      map_chunk: (m) => this.#checkMapChunk(m),
      error: (m) => this.#checkError(m),
    };
  }

  /** Fetch the definition the server serves. */
  static async load(url = "/protocol.json") {
    const response = await fetch(url, { cache: "no-cache" });
    if (!response.ok) throw new Error(`cannot load the protocol from ${url}: HTTP ${response.status}`);
    return new Protocol(await response.json());
  }

  /**
   * Check a message against protocol.json and return it.
   * @param {object} message
   * @param {string|null} direction CLIENT_TO_SERVER / SERVER_TO_CLIENT refuses the other side's
   *   messages (unknown_type); null accepts both.
   * @param {{strict?: boolean}} options strict: refuse fields the spec does not list (sending).
   */
  validate(message, direction = null, { strict = false } = {}) {
    if (!isPlainObject(message) || typeof message.type !== "string") {
      fail("malformed_message", "a message is a map with a str 'type' field");
    }
    const kind = message.type;
    const spec = Object.hasOwn(this.messages, kind) ? this.messages[kind] : null;
    if (spec === null || (direction !== null && spec.direction !== direction)) {
      fail("unknown_type", `no ${direction ?? "protocol"} message '${kind}'`);
    }
    if (kind === "hello" && Number.isInteger(message.version) && message.version !== this.version) {
      fail("version_mismatch", `client speaks ${message.version}, protocol ${this.version}`);
    }
    for (const field of spec.fields) {
      if (message[field.name] !== undefined) checkValue(message[field.name], field, `${kind}.${field.name}`);
      else if (field.required) fail("missing_field", `${kind} needs field '${field.name}'`);
    }
    if (strict) {
      const known = new Set(["type", ...spec.fields.map((f) => f.name)]);
      const extra = Object.keys(message).filter((k) => !known.has(k));
      if (extra.length) fail("invalid_field", `${kind} has unknown fields ${extra.join(", ")}`);
    }
    this.semantic[kind]?.(message);
    return message;
  }

  /** Validate strictly and pack one message -> Uint8Array; message_too_big over maxBytes. */
  encode(message, maxBytes = this.limits.max_message_bytes) {
    this.validate(message, null, { strict: true });
    const data = msgpackEncode(message, { ignoreUndefined: true });
    if (data.byteLength > maxBytes) fail("message_too_big", `${data.byteLength} bytes, limit ${maxBytes}`);
    return data;
  }

  /** Unpack and validate one message (ArrayBuffer or Uint8Array); size checked first. */
  decode(data, direction = null, maxBytes = this.limits.max_message_bytes) {
    const bytes = data instanceof Uint8Array ? data : new Uint8Array(data);
    if (bytes.byteLength > maxBytes) fail("message_too_big", `${bytes.byteLength} bytes, limit ${maxBytes}`);
    let message;
    try {
      message = msgpackDecode(bytes);
    } catch (exc) {
      fail("malformed_message", `not one msgpack object: ${exc.message}`);
    }
    return this.validate(message, direction);
  }

  // ---- what the schema cannot say (as protocol.py's _check_* functions) ----------------------

  #checkHello(m) {
    const { min_image_side: lo, max_image_side: hi } = this.limits;
    for (const key of ["colour_size", "depth_size"]) {
      if (!m[key].every((side) => side >= lo && side <= hi)) {
        fail("bad_image_size", `${key} ${m[key]} outside [${lo}, ${hi}] px`);
      }
    }
    const [[cw, ch], [dw, dh]] = [m.colour_size, m.depth_size];
    if (Math.abs(dw / dh / (cw / ch) - 1) > this.limits.max_aspect_difference) {
      fail("bad_image_size", `depth ${dw}x${dh} and colour ${cw}x${ch} have different aspect ratios`);
    }
    const [fx, fy, cx, cy] = m.intrinsics;
    const { min_focal_ratio: fLo, max_focal_ratio: fHi } = this.limits;
    if (!(fLo * cw <= fx && fx <= fHi * cw && fLo * ch <= fy && fy <= fHi * ch)) {
      fail("bad_intrinsics", `fx ${fx}, fy ${fy} implausible for ${cw}x${ch}: need fx/width and ` +
        `fy/height in [${fLo}, ${fHi}]`);
    }
    if (Math.max(fx, fy) / Math.min(fx, fy) > this.limits.max_focal_aspect) {
      fail("bad_intrinsics", `fx ${fx} and fy ${fy} differ too much`);
    }
    if (m.gravity !== undefined && !(Math.hypot(...m.gravity) > 1e-6)) {
      fail("invalid_field", "gravity must be a non-zero vector");
    }
    if (!(cx >= 0 && cx <= cw && cy >= 0 && cy <= ch)) {
      fail("bad_intrinsics", `principal point (${cx}, ${cy}) outside ${cw}x${ch}`);
    }
  }

  #checkCommand(m) {
    const needs = { goto: "target", goto_pixel: "pixel", sticks: "sticks", flight_mode: "flight_mode" }[m.name];
    if (needs && m[needs] === undefined) fail("bad_command", `${m.name} needs the field '${needs}'`);
  }

  #checkMapChunk(m) {
    if (m.count > this.limits.max_map_chunk_points) {
      fail("invalid_field", `map_chunk has ${m.count} points, more than the limit`);
    }
    if (m.points.byteLength !== 12 * m.count || m.colours.byteLength !== 3 * m.count) {
      fail("invalid_field", `map_chunk points/colours lengths do not match ${m.count}`);
    }
  }

  #checkError(m) {
    if (this.errorNames[m.code] !== m.name) fail("invalid_field", `error code ${m.code} is not '${m.name}'`);
  }

  // ---- builders of the client's messages ------------------------------------------------------

  /**
   * @param {object} p
   * @param {string} p.clientName free text, 1..64 characters
   * @param {number[]} p.intrinsics [fx, fy, cx, cy] of the colour image, pixels
   * @param {number[]} p.colourSize [width, height] px; p.depthSize likewise (default: colour's)
   * @param {number} p.depthScale depth units per metre (1000: millimetres)
   * @param {number[]} [p.gravity] gravity in the first camera frame (x right, y down, z forward)
   * @param {boolean} [p.recorded] the frames come from a recording: the server queues them
   *   rather than keeping only the newest (the welcome's queued_frames says how many)
   */
  hello({ clientName, intrinsics, colourSize, depthSize = colourSize, depthScale = 1000, gravity, recorded }) {
    const message = {
      type: "hello",
      version: this.version,
      client_name: clientName,
      intrinsics: Array.from(intrinsics, Number),
      colour_size: Array.from(colourSize, Math.round),
      depth_size: Array.from(depthSize, Math.round),
      depth_scale: depthScale,
    };
    if (gravity) message.gravity = Array.from(gravity, Number);
    if (recorded) message.recorded = true;
    return this.validate(message, CLIENT_TO_SERVER, { strict: true });
  }

  /**
   * @param {object} p
   * @param {number} p.seq strictly increasing within the session
   * @param {number} p.timestamp capture time on the client's monotonic clock, seconds
   * @param {Uint8Array} p.colour baseline JPEG
   * @param {Uint8Array} p.depth uint16 depth as depthFormat says
   * @param {"png"|"zlib"} p.depthFormat
   * @param {number} [p.depthScale] units per metre, when not the hello's
   * @param {number[]} [p.deviceCamera] T_device_camera: the device's own camera pose in its world,
   *   16 numbers, row-major, metres, this protocol's camera axes (x right, y down, z forward)
   * @param {number} [p.deviceWorld] which of the device's worlds deviceCamera is in: a new number
   *   after the device's own tracking restarted (its poses may have jumped)
   */
  frame({ seq, timestamp, colour, depth, depthFormat, depthScale, deviceCamera, deviceWorld }) {
    const message = { type: "frame", seq, timestamp, colour, depth, depth_format: depthFormat };
    if (depthScale !== undefined) message.depth_scale = depthScale;
    if (deviceCamera) message.T_device_camera = Array.from(deviceCamera, Number);
    if (deviceWorld) message.device_world = deviceWorld;
    return this.validate(message, CLIENT_TO_SERVER, { strict: true });
  }

  /** A drone command: `fields` are target, pixel, seq, sticks, speed, flight_mode as the name needs. */
  command(id, name, fields = {}) {
    const message = { type: "command", id, name };
    for (const [key, value] of Object.entries(fields)) {
      if (value === undefined || value === null) continue;
      message[key] = Array.isArray(value) || ArrayBuffer.isView(value) ? Array.from(value, Number) : value;
    }
    return this.validate(message, CLIENT_TO_SERVER, { strict: true });
  }

  bye(reason) {
    const message = { type: "bye" };
    if (reason) message.reason = String(reason).slice(0, 256);
    return this.validate(message, CLIENT_TO_SERVER, { strict: true });
  }

  // ---- readers ----------------------------------------------------------------------------------

  /** Whether an error name is fatal, and the close code that follows it. */
  errorInfo(name) {
    return this.errors[name] ?? { name, fatal: false, close: null, meaning: "unknown error" };
  }

  /** What a client does after a close with this code (protocol.json's close_codes[].reconnect):
   * "never" (final), "retry" (with back-off), "when_active" (on its next frame or command) or
   * "when_asked" (on the user's own request). Codes it does not list (1006...) are "retry". */
  reconnectAfter(code) {
    return this.closeCodes[code]?.reconnect ?? "retry";
  }

  /** The name and meaning of a WebSocket close code (protocol's or the standard ones). */
  closeReason(code) {
    const standard = { 1000: "normal closure", 1001: "going away", 1006: "connection lost", 1011: "server error" };
    const known = this.closeCodes[code];
    return known ? `${known.name}: ${known.meaning}` : standard[code] ?? `close code ${code}`;
  }
}

/** map_chunk points as float32 (x, y, z) and colours as uint8 (r, g, b), copied out of the
 * message buffer (msgpack's views may sit at an odd offset; Float32Array needs a multiple of 4). */
export function mapChunkArrays(chunk) {
  const points = new Float32Array(chunk.count * 3);
  const view = new DataView(chunk.points.buffer, chunk.points.byteOffset, chunk.points.byteLength);
  for (let i = 0; i < points.length; i++) points[i] = view.getFloat32(4 * i, true);
  return { points, colours: chunk.colours.slice() };
}
