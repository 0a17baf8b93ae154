// The fused map as a triangle mesh on the page, for the views that draw the room itself (FPV)
// or hide the drone behind it (AR occlusion without depth). The server extracts the mesh from
// its TSDF on each request (marching cubes over the whole map, in the mapper process that fusion
// also waits for), so the page asks rarely: only while a view wants the mesh, one request at a
// time, no sooner than MESH_REFRESH.minIntervalMs after the previous one, and only when the map
// grew by MESH_REFRESH.minNewPoints preview points since (map_chunk counts) or, the first time,
// once the server says that its map has a surface (map_chunk.surface: before it, the request
// would only get a 409). A server that does not say is asked once the preview has
// minNewPoints points.

import * as THREE from "three";
import { parseMeshPly } from "../formats/ply.js";

export const MESH_REFRESH = Object.freeze({
  minIntervalMs: 8000, // between the end of one download and the start of the next
  minNewPoints: 2000, // map preview points added since the mesh in hand was asked for
  retryMs: 4000, // after a failed request
  timeoutMs: 60000, // a download that has not come by then is given up, and asked for again
});

export class MapMesh extends EventTarget {
  /** @param {{download: (name: string) => Promise<{blob: Blob}>}} client the session client */
  constructor(client) {
    super();
    this.client = client;
    this.wanted = false; // a view needs the mesh now
    this.geometry = null; // THREE.BufferGeometry in the world frame, or null
    this.mapPoints = 0; // preview points the map has (map_chunk totals)
    this.surface = null; // the server's map has a surface (map_chunk.surface); null: not said
    this.loadedAtPoints = -1; // mapPoints when the mesh in hand was asked for
    this.pending = false;
    this.nextAllowed = 0; // performance.now() before which no request starts
    this.downloads = 0; // requests made (tests check the rate)
    this.failures = 0;
    this.lastError = null;
    this.lastDownload = null; // {ms, bytes} of the last mesh that came
  }

  /** Track the map's size in the session state (session/state.js); a new session drops the mesh. */
  follow(state) {
    state.addEventListener("map", ({ detail: { total, reset, surface } }) => this.noteMapPoints(total, reset, surface));
    state.addEventListener("reset", () => this.clear());
  }

  /** The map's size in preview points (after each map_chunk) and whether it has a surface
   * (null: not said); a reset map drops the mesh. */
  noteMapPoints(total, reset = false, surface = null) {
    if (reset) this.clear();
    this.mapPoints = total;
    if (surface !== null && surface !== undefined) this.surface = surface;
  }

  clear() {
    this.geometry?.dispose();
    this.geometry = null;
    this.loadedAtPoints = -1;
    this.surface = null;
    this.dispatchEvent(new CustomEvent("mesh", { detail: null }));
  }

  /** Start a download when one is due; cheap to call every animation frame. */
  poll(now = performance.now()) {
    if (!this.wanted || this.pending || now < this.nextAllowed) return;
    const surface = this.surface ?? this.mapPoints >= MESH_REFRESH.minNewPoints;
    if (!surface) return;
    const grown = this.loadedAtPoints < 0 || this.mapPoints - this.loadedAtPoints >= MESH_REFRESH.minNewPoints;
    if (!grown) return;
    this.#download(this.mapPoints);
  }

  async #download(atPoints) {
    this.pending = true;
    this.downloads += 1;
    const t0 = performance.now();
    try {
      const { blob } = await this.client.download("mesh.ply", AbortSignal.timeout(MESH_REFRESH.timeoutMs));
      this.lastDownload = { ms: performance.now() - t0, bytes: blob.size }; // the server's extraction included
      const { positions, colours, indices } = parseMeshPly(await blob.arrayBuffer());
      const geometry = new THREE.BufferGeometry();
      geometry.setAttribute("position", new THREE.BufferAttribute(positions, 3));
      geometry.setAttribute("color", new THREE.BufferAttribute(colours, 3, true));
      geometry.setIndex(new THREE.BufferAttribute(indices, 1));
      geometry.computeBoundingSphere();
      const old = this.geometry;
      this.geometry = geometry;
      this.loadedAtPoints = atPoints;
      this.dispatchEvent(new CustomEvent("mesh", { detail: geometry }));
      old?.dispose(); // after the views switched to the new one
      this.nextAllowed = performance.now() + MESH_REFRESH.minIntervalMs;
    } catch (exc) {
      this.failures += 1;
      this.lastError = exc.message;
      this.nextAllowed = performance.now() + MESH_REFRESH.retryMs;
    } finally {
      this.pending = false;
    }
  }

  /** What the tests and the debugging snapshot read. */
  summary() {
    return { downloads: this.downloads, failures: this.failures, lastError: this.lastError, wanted: this.wanted,
      triangles: this.geometry ? this.geometry.index.count / 3 : 0, loadedAtPoints: this.loadedAtPoints, surface: this.surface,
      lastDownload: this.lastDownload };
  }
}
