"""``GET /api/phone-link``: how a phone opens this server."""

from __future__ import annotations

from pydantic import Field

from server.transport.schemas.common import WireModel


class PhoneLinkBody(WireModel):
    """``GET /api/phone-link``: how a phone on the local network opens this server (the link
    and notes ``serve`` prints)."""

    urls: list[str] = Field(
        description="the page's URLs on this machine's LAN addresses (and the hosts the "
        "operator named, `server.phone_hosts`), best first; `/api/phone-link.svg` is the first's "
        "QR code. Empty when no phone can reach the server (it listens on loopback only)"
    )
    tls: bool = Field(description="served over HTTPS (a secure origin: camera and depth work)")
    notes: list[str] = Field(description="what the phone's user must know, a sentence each")
