// The QR code of an invitation link, made in the page: the link carries a join token in its
// fragment, which must never travel to a server (the phone-link card shows the server's code of
// its own URL, /api/phone-link.svg, which holds no secret). uqr (npm) encodes it.
import { encode } from "uqr";

const QUIET = 4; // light modules around the code, as the standard asks

/** The QR code of `text` (error correction M) as an SVG document: dark modules on white,
 * with the quiet zone. */
export function qrSvg(text) {
  const { data, size } = encode(text, { ecc: "M", border: 0 });
  const side = size + 2 * QUIET;
  const path = [];
  data.forEach((row, y) => row.forEach((dark, x) => {
    if (dark) path.push(`M${x + QUIET},${y + QUIET}h1v1h-1z`);
  }));
  return `<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 ${side} ${side}" shape-rendering="crispEdges">` +
    `<rect width="${side}" height="${side}" fill="#fff"/><path d="${path.join("")}" fill="#000"/></svg>`;
}
