"""The phone link route (``/api/phone-link``) of a real server on loopback: the phone URLs and the
first one's QR code, or why there is none (the link itself:
tests/unit/transport/test_phone_link.py)."""

from __future__ import annotations

import httpx

from server.transport import phone_link as pl


def test_the_phone_link_route_gives_the_urls_and_the_first_ones_qr_code(live_server):
    server = live_server(phone_hosts=["laptop.lan"])
    body = httpx.get(f"{server.url}/api/phone-link").json()
    url = f"http://laptop.lan:{server.port}/"
    assert body["urls"] == [url] and body["tls"] is False
    assert any("no camera" in n for n in body["notes"])
    svg = httpx.get(f"{server.url}/api/phone-link.svg")
    assert svg.status_code == 200 and svg.headers["content-type"].startswith("image/svg+xml")
    assert svg.content == pl.qr_svg(url)  # the code of that URL (decoded above)


def test_the_phone_link_route_of_a_loopback_server_says_why_there_is_no_code(live_server):
    server = live_server()
    body = httpx.get(f"{server.url}/api/phone-link").json()
    assert body["urls"] == [] and "--host 0.0.0.0" in body["notes"][0]
    svg = httpx.get(f"{server.url}/api/phone-link.svg")
    assert svg.status_code == 404 and svg.json()["error"]["code"] == "not_found"
