"""The page's "open on your phone" card: on a desktop-size page, the QR code of the phone URL
(read back from a screenshot) until the page streams itself; on a phone, nothing; on a server
only a local browser reaches, the reason instead of a code."""

from __future__ import annotations

import cv2

from tests.support.browser import DESKTOP, PHONE, REPLAY_PATH, start_replay

CARD = "#phone-link"


def test_the_desktop_page_shows_the_phone_urls_qr_code_until_it_streams(live_server, open_page):
    server = live_server(phone_hosts=["laptop.lan"])
    page = open_page(server, REPLAY_PATH, **DESKTOP)
    page.page.wait_for_function(
        f"document.querySelector('{CARD} img')?.complete === true", timeout=10_000
    )
    url = f"http://laptop.lan:{server.port}/"
    assert page.page.inner_text(f"{CARD} code") == url
    assert "no camera" in page.page.inner_text(CARD)
    rgb = page.screenshot("phone-link-card.png", f"{CARD} img")
    gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    # Black and white, as a phone's reader sees it: the browser scales the SVG with grey edges on
    # its modules, which OpenCV's detector misreads now and then (a CI run decoded nothing).
    binary = cv2.threshold(gray, 128, 255, cv2.THRESH_BINARY)[1]
    padded = cv2.copyMakeBorder(binary, 40, 40, 40, 40, cv2.BORDER_CONSTANT, value=255)
    assert cv2.QRCodeDetector().detectAndDecode(padded)[0] == url

    # Once this page streams, its own picture replaces the invitation.
    start_replay(page, 3)
    page.page.wait_for_selector(CARD, state="hidden", timeout=10_000)
    assert not page.errors, page.errors


def test_a_phone_size_page_shows_no_card_and_a_loopback_server_says_why(live_server, open_page):
    phone_server = live_server(phone_hosts=["laptop.lan"])
    phone = open_page(phone_server, **PHONE)
    phone.page.wait_for_timeout(500)  # the card would come with the first fetch
    assert phone.page.locator(CARD).count() == 0

    desktop = open_page(live_server(), **DESKTOP)  # listens on 127.0.0.1 alone
    desktop.page.wait_for_selector(CARD, timeout=10_000)
    assert desktop.page.locator(f"{CARD} img").count() == 0
    assert "--host 0.0.0.0" in desktop.page.inner_text(CARD)
    assert not phone.errors and not desktop.errors, phone.errors + desktop.errors
