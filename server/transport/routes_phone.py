"""The desktop page's "open on your phone" link: the URLs a phone on the LAN opens and the QR
code of the first (server/transport/phone_link.py, the same that ``serve`` prints).

| path | what |
|---|---|
| ``/api/phone-link`` | the URLs, whether TLS is on, and notes for the phone's user |
| ``/api/phone-link.svg`` | the QR code of the first URL; 404 when there is none |
"""

from __future__ import annotations

import asyncio

from fastapi import APIRouter, HTTPException, Response

from server.transport.deps import SettingsDep
from server.transport.phone_link import PhoneLink, phone_link, qr_svg
from server.transport.schemas import ErrorBody, PhoneLinkBody

router = APIRouter(tags=["client"])


async def _link(settings) -> PhoneLink:
    # Looked up on each request: the machine's addresses change when it joins another network.
    # The look-up makes system calls (and may resolve the host name): off the event loop.
    return await asyncio.to_thread(
        phone_link, settings.host, settings.port, settings.tls, settings.phone_hosts
    )


@router.get("/api/phone-link", response_model=PhoneLinkBody)
async def phone_link_info(settings: SettingsDep) -> PhoneLinkBody:
    """The URLs a phone on the same network opens (best first), whether they are HTTPS, and
    what its user must know (accept the self-signed certificate once; no camera without
    TLS; the server listens on loopback only)."""
    link = await _link(settings)
    return PhoneLinkBody(urls=link.urls, tls=link.tls, notes=link.notes)


@router.get(
    "/api/phone-link.svg",
    response_class=Response,
    responses={
        200: {"content": {"image/svg+xml": {}}, "description": "the first URL's QR code"},
        404: {"model": ErrorBody, "description": "`not_found`: no phone can reach the server"},
    },
)
async def phone_link_qr(settings: SettingsDep) -> Response:
    """The QR code of the first URL of `/api/phone-link`, as SVG (scaled by its viewBox)."""
    link = await _link(settings)
    if not link.urls:
        raise HTTPException(404, link.notes[0])
    return Response(
        qr_svg(link.urls[0]), media_type="image/svg+xml", headers={"Cache-Control": "no-cache"}
    )
