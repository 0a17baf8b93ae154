// "Open on your phone": on a desktop-size page, the URL a phone on the same network opens, as a
// QR code (the server's /api/phone-link and its .svg: the same code `serve` prints in the
// terminal). A phone-size page, or a viewer link, shows nothing; css/app.css hides the card
// once the AR view shows a picture.

// A mouse and a wide window: the page on a laptop, where a phone's camera can read the code.
const DESKTOP = "(pointer: fine) and (min-width: 900px)";

/**
 * Add the phone-link card to `parent` (an element of the page that is positioned).
 * Resolves to the card, or null when there is nothing to show (phone-size page, no server
 * answer).
 */
export async function showPhoneLink(parent) {
  if (!window.matchMedia(DESKTOP).matches) return null;
  let link;
  try {
    const answer = await fetch("/api/phone-link");
    if (!answer.ok) return null;
    link = await answer.json();
  } catch {
    return null; // an older server without the route: the page works without the card
  }
  const card = document.createElement("aside");
  card.id = "phone-link";
  card.className = "phone-link";
  card.setAttribute("aria-label", "open this page on a phone");
  const close = document.createElement("button");
  close.type = "button";
  close.className = "phone-link-close";
  close.title = "hide";
  close.textContent = "×";
  close.addEventListener("click", () => card.remove());
  const title = document.createElement("b");
  title.textContent = "Open on your phone";
  card.append(close, title);
  if (link.urls.length) {
    const code = document.createElement("img");
    code.src = "/api/phone-link.svg";
    code.alt = `QR code of ${link.urls[0]}`;
    const url = document.createElement("code");
    url.textContent = link.urls[0];
    card.append(code, url);
  }
  for (const note of link.notes) {
    const line = document.createElement("small");
    line.textContent = note;
    card.append(line);
  }
  parent.append(card);
  return card;
}
