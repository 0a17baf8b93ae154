// The server's trajectory download (GET /api/sessions/{id}/trajectory.tum), so that a page
// reopened into a running session draws the camera's path so far: one "t tx ty tz qx qy qz qw"
// line per pose (TUM RGB-D format: seconds, metres, a unit quaternion), "#" lines are comments.

/** Camera positions [x, y, z] (world frame, metres) of a TUM trajectory. */
export function parseTumPositions(text) {
  const positions = [];
  for (const line of text.split(/\r?\n/)) {
    if (!line.trim() || line.startsWith("#")) continue;
    const v = line.trim().split(/\s+/).map(Number);
    if (v.length >= 8 && v.every(Number.isFinite)) positions.push([v[1], v[2], v[3]]);
  }
  return positions;
}
