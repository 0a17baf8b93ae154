"""How a phone on the local network finds this server: the machine's LAN addresses, the URLs a
phone opens, what its user must know, and the QR code that carries the first URL (segno).

``serve`` prints the link and its QR code in the terminal; ``GET /api/phone-link`` (and its
``.svg``) give the desktop page the same, so both show one code."""

from __future__ import annotations

import io
import ipaddress
import logging
import socket
import struct
import sys
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

import segno

log = logging.getLogger(__name__)

WILDCARDS = ("0.0.0.0", "", "::")  # a server bound here listens on every interface
LOOPBACK_NAMES = ("localhost",)
# Interfaces of containers and virtual machines on this machine: their addresses are private to
# it, a phone never reaches them, and a URL with one would only mislead.
VIRTUAL_INTERFACES = ("docker", "br-", "veth", "virbr", "cni", "flannel", "podman")
# The default route's source address is found by connecting a UDP socket to an address that is
# only looked up in the routing table, never sent to (connect() on UDP sends nothing).
_ROUTE_PROBE = ("192.0.2.1", 9)  # TEST-NET-1 (RFC 5737), the discard port
_SIOCGIFADDR = 0x8915  # Linux ioctl: an interface's IPv4 address


@dataclass(frozen=True)
class PhoneLink:
    """What a phone on the LAN opens. urls: best first (the QR code carries the first); empty
    when no phone can reach the server. notes: what its user must know, one sentence each."""

    urls: list[str]
    tls: bool
    notes: list[str] = field(default_factory=list)


def lan_addresses() -> list[str]:
    """This machine's IPv4 addresses that another machine on its networks may reach (no
    loopback, link-local or container bridge), the default route's first."""
    found: list[str] = []
    for address in (*_route_address(), *_interface_addresses(), *_hostname_addresses()):
        ip = ipaddress.ip_address(address)
        if not (ip.is_loopback or ip.is_link_local or ip.is_unspecified) and address not in found:
            found.append(address)
    return found


def in_container() -> bool:
    """Whether this process runs in a Docker or Podman container (the files they create)."""
    return Path("/.dockerenv").exists() or Path("/run/.containerenv").exists()


def phone_hosts(
    host: str, extra: Iterable[str] = (), detect: Callable[[], list[str]] = lan_addresses
) -> list[str]:
    """The hosts a phone reaches a server bound to ``host`` by, best first: ``extra`` (named by
    the operator), then the bound address itself, or this machine's LAN addresses when it
    listens on every interface. A server bound to loopback alone has only ``extra``."""
    hosts = list(dict.fromkeys(extra))
    if host in WILDCARDS:
        hosts += [a for a in detect() if a not in hosts]
    elif not _is_loopback(host) and host not in hosts:
        hosts.append(host)
    return hosts


def certificate_hosts(
    host: str, extra: Iterable[str] = (), detect: Callable[[], list[str]] = lan_addresses
) -> list[str]:
    """Every host a phone may reach this machine by, for the TLS certificate: ``extra``, the
    bound address and this machine's LAN addresses, whatever the server binds to (a later
    ``--host 0.0.0.0`` then needs no new certificate, which the phone would have to accept)."""
    hosts = list(dict.fromkeys([*extra, *detect()]))
    if host not in WILDCARDS and host not in hosts:
        hosts.append(host)
    return hosts


def phone_link(
    host: str,
    port: int,
    tls: bool,
    extra: Iterable[str] = (),
    detect: Callable[[], list[str]] = lan_addresses,
    contained: Callable[[], bool] = in_container,
) -> PhoneLink:
    """The URLs and notes for a server bound to ``host``:``port`` (``extra``: hosts the
    operator names, e.g. a container's host's LAN address)."""
    scheme = "https" if tls else "http"
    extra = list(extra)
    hosts = phone_hosts(host, extra, detect)
    urls = [f"{scheme}://{_url_host(h)}:{port}/" for h in hosts]
    notes = []
    if not extra and urls and contained():
        notes.append(
            "this server runs in a container, whose addresses a phone cannot reach: name the "
            "host's LAN address with DRONESIM_PHONE_HOSTS (or --phone-host)"
        )
    if not urls and host not in WILDCARDS:
        notes.append(
            f"the server listens on {host} only: a phone cannot reach it; "
            "start it with --host 0.0.0.0 (and --tls for the camera)"
        )
    elif not urls:
        notes.append(
            "no LAN address found on this machine: is it on a network? "
            "(--phone-host names the address phones reach it by)"
        )
    if tls:
        notes.append(
            "the certificate is self-signed: the phone must accept it once "
            "(and again whenever the server makes a new one)"
        )
    else:
        notes.append(
            "without --tls the phone gets no camera and no depth (both need a secure origin): "
            "only the replay modes work"
        )
    return PhoneLink(urls, tls, notes)


def qr_svg(url: str) -> bytes:
    """The QR code of ``url`` as SVG, black on white, sized by its viewBox (the page scales
    it); four modules of quiet zone, as readers need."""
    out = io.BytesIO()
    _qr(url).save(
        out, kind="svg", border=4, omitsize=True, xmldecl=False, dark="#000", light="#fff"
    )
    return out.getvalue()


def qr_png(url: str, scale: int = 8) -> bytes:
    """The QR code of ``url`` as a PNG, ``scale`` pixels a module (tests decode it)."""
    out = io.BytesIO()
    _qr(url).save(out, kind="png", scale=scale, border=4)
    return out.getvalue()


def qr_text(url: str) -> str:
    """The QR code of ``url`` for a terminal: two modules a character (half blocks), so it fits
    an 80-column terminal for any URL ``serve`` prints."""
    out = io.StringIO()
    _qr(url).terminal(out=out, compact=True, border=2)
    return out.getvalue()


def _qr(url: str) -> segno.QRCode:
    # Medium error correction: readable off a screen at an angle; never a Micro QR, which
    # phone cameras do not read.
    return segno.make(url, error="m", micro=False)


def _is_loopback(host: str) -> bool:
    if host.lower() in LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def _url_host(host: str) -> str:
    """An IPv6 address goes in brackets in a URL."""
    return f"[{host}]" if ":" in host else host


def _route_address() -> list[str]:
    """The address this machine's default route leaves from (none without a route)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        try:
            probe.connect(_ROUTE_PROBE)
            return [probe.getsockname()[0]]
        except OSError:
            return []


def _interface_addresses() -> list[str]:
    """The IPv4 address of each network interface that is not a container's or a VM's (Linux;
    elsewhere none: the default route's address is the one that matters)."""
    if not sys.platform.startswith("linux"):
        return []
    import fcntl

    found = []
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        for _, name in socket.if_nameindex():
            if name.startswith(VIRTUAL_INTERFACES):
                continue
            try:
                # struct ifreq: the name in 16 bytes, then a sockaddr_in (address at 20..24).
                answer = fcntl.ioctl(s.fileno(), _SIOCGIFADDR, struct.pack("256s", name.encode()))
            except OSError:  # an interface without an IPv4 address
                continue
            found.append(socket.inet_ntoa(answer[20:24]))
    return found


def _hostname_addresses() -> list[str]:
    """What this machine's name resolves to (often only 127.0.1.1 on Debian, hence the two
    other ways)."""
    try:
        infos = socket.getaddrinfo(socket.gethostname(), None, socket.AF_INET)
    except OSError:
        return []
    return [str(sockaddr[0]) for *_, sockaddr in infos]
