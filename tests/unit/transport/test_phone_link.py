"""Phones on the LAN: the TLS certificate names the addresses a phone reaches this machine by and
is made anew when they change; the phone URL and its QR code, as ``serve`` prints them and as the
desktop page gets them (``/api/phone-link``: tests/server/test_phone_link_server.py); the
``phone_hosts`` setting."""

from __future__ import annotations

import datetime as dt
import ipaddress
import os
import re
import shutil
import socket
import ssl
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID

from server.client.server_process import free_port
from server.config import load_config
from server.errors import ConfigError
from server.transport import phone_link as pl
from server.transport.tls import certificate_hosts, ensure_certificate
from tests.support.paths import REPO

# ---- helpers ------------------------------------------------------------------------------------


def names_in(pem: bytes) -> set[str]:
    """The subject alternative names of a PEM certificate, as text."""
    alt = (
        x509.load_pem_x509_certificate(pem)
        .extensions.get_extension_for_class(x509.SubjectAlternativeName)
        .value
    )
    return {*alt.get_values_for_type(x509.DNSName)} | {
        str(a) for a in alt.get_values_for_type(x509.IPAddress)
    }


def interface_addresses() -> set[str]:
    """This machine's global IPv4 addresses as ``ip`` lists them (the oracle for detection),
    without container bridges."""
    ip = shutil.which("ip")
    if ip is None:
        pytest.skip("no `ip` command to list this machine's addresses")
    out = subprocess.run(
        [ip, "-4", "-o", "addr", "show", "scope", "global"], capture_output=True, text=True
    ).stdout
    found = set()
    for line in out.splitlines():
        _, name, _, cidr, *_ = line.split()
        if not name.startswith(pl.VIRTUAL_INTERFACES):
            found.add(cidr.split("/")[0])
    return found


def decode_qr(gray: np.ndarray) -> str:
    """The text of the one QR code in a grey picture (OpenCV's detector), "" if none is read."""
    padded = cv2.copyMakeBorder(gray, 40, 40, 40, 40, cv2.BORDER_CONSTANT, value=255)
    text, _, _ = cv2.QRCodeDetector().detectAndDecode(padded)
    return text


def decode_terminal_qr(lines: list[str]) -> str:
    """Decode a QR code printed with half blocks (two modules a character; a drawn half is a
    light module, as segno draws for dark terminals)."""
    halves = {"█": (255, 255), "▀": (255, 0), "▄": (0, 255), " ": (0, 0)}
    rows = []
    for line in lines:
        pairs = [halves[c] for c in line]
        rows += [[p[0] for p in pairs], [p[1] for p in pairs]]
    modules = np.array(rows, np.uint8)
    return decode_qr(cv2.resize(modules, None, fx=8, fy=8, interpolation=cv2.INTER_NEAREST))


def self_signed(folder: Path, hosts: list[str], not_after: dt.datetime) -> None:
    """A certificate for ``hosts`` with its key in ``folder``, valid until ``not_after``."""
    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "test")])
    alt = [
        x509.IPAddress(ipaddress.ip_address(h)) if h[0].isdigit() else x509.DNSName(h)
        for h in hosts
    ]
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(not_after - dt.timedelta(days=30))
        .not_valid_after(not_after)
        .add_extension(x509.SubjectAlternativeName(alt), critical=False)
        .sign(key, hashes.SHA256())
    )
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "cert.pem").write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    (folder / "key.pem").write_bytes(
        key.private_bytes(
            serialization.Encoding.PEM,
            serialization.PrivateFormat.PKCS8,
            serialization.NoEncryption(),
        )
    )


# ---- the certificate ----------------------------------------------------------------------------


def test_the_certificate_names_the_given_hosts_and_this_machine(tmp_path):
    made = ensure_certificate(tmp_path, ["127.0.0.2", "Phone.Example"])
    names = names_in(made.cert.read_bytes())
    assert {"127.0.0.2", "phone.example", "127.0.0.1", "localhost"} <= names
    assert socket.gethostname().lower() in names
    assert made.issued and set(made.hosts) == names
    assert made.key.stat().st_mode & 0o077 == 0  # the key is the owner's alone


def test_the_certificate_names_the_lan_addresses_this_machine_has(tmp_path):
    """What serve asks for (certificate_hosts) holds every address ``ip`` lists, so a phone
    that reaches any of them gets a certificate naming it."""
    addresses = interface_addresses()
    detected = pl.lan_addresses()
    assert addresses <= set(detected), f"ip lists {addresses}, detected {detected}"
    assert not [a for a in detected if ipaddress.ip_address(a).is_loopback]
    made = ensure_certificate(tmp_path, pl.certificate_hosts("0.0.0.0", ["192.0.2.200"]))
    assert addresses | {"192.0.2.200"} <= names_in(made.cert.read_bytes())


def test_a_certificate_that_names_every_host_is_kept(tmp_path):
    first = ensure_certificate(tmp_path, ["127.0.0.2"])
    pem = first.cert.read_bytes()
    again = ensure_certificate(tmp_path, ["127.0.0.2"])
    assert not again.issued and again.cert.read_bytes() == pem
    assert not ensure_certificate(tmp_path, []).issued  # fewer hosts: still named


def test_a_new_address_makes_a_new_certificate_that_still_names_the_old(tmp_path):
    """The laptop joined another network: a new certificate, naming the new address and the old
    one, so coming back to the first network needs no third."""
    first = ensure_certificate(tmp_path, ["127.0.0.2"])
    pem = first.cert.read_bytes()
    moved = ensure_certificate(tmp_path, ["127.0.0.3"])
    assert moved.issued and moved.cert.read_bytes() != pem
    assert {"127.0.0.2", "127.0.0.3"} <= names_in(moved.cert.read_bytes())
    assert not ensure_certificate(tmp_path, ["127.0.0.2"]).issued


@pytest.mark.parametrize("days_left", [-1, 0.5])
def test_an_expired_or_expiring_certificate_is_made_anew(tmp_path, days_left):
    now = dt.datetime.now(dt.timezone.utc)
    self_signed(tmp_path, ["localhost", "127.0.0.1"], now + dt.timedelta(days=days_left))
    made = ensure_certificate(tmp_path, [])
    assert made.issued
    cert = x509.load_pem_x509_certificate(made.cert.read_bytes())
    assert cert.not_valid_after_utc > now + dt.timedelta(days=800)


def test_a_certificate_not_matching_its_key_or_unreadable_is_made_anew(tmp_path):
    ensure_certificate(tmp_path, [])
    other = tmp_path / "other"
    ensure_certificate(other, [])
    (tmp_path / "key.pem").write_bytes((other / "key.pem").read_bytes())  # a half-done write
    made = ensure_certificate(tmp_path, [])
    assert made.issued
    ctx = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    ctx.load_cert_chain(made.cert, made.key)  # raises if they do not belong together
    (tmp_path / "cert.pem").write_text("not a certificate")
    assert ensure_certificate(tmp_path, []).issued
    assert "localhost" in certificate_hosts(tmp_path / "cert.pem")


# ---- the phone link -----------------------------------------------------------------------------


def lan():
    return ["192.0.2.7", "198.51.100.4"]


def test_a_server_on_every_interface_is_opened_at_the_lan_addresses():
    link = pl.phone_link("0.0.0.0", 8443, True, detect=lan)
    assert link.urls == ["https://192.0.2.7:8443/", "https://198.51.100.4:8443/"]
    assert any("accept it once" in n for n in link.notes)


def test_the_hosts_the_operator_names_come_first_and_ipv6_is_bracketed():
    link = pl.phone_link("0.0.0.0", 8000, False, ["laptop.lan", "fd00::5"], detect=lan)
    assert link.urls[:2] == ["http://laptop.lan:8000/", "http://[fd00::5]:8000/"]
    assert link.urls[2:] == ["http://192.0.2.7:8000/", "http://198.51.100.4:8000/"]
    assert any("no camera" in n and "--tls" in n for n in link.notes)


def test_a_server_on_loopback_says_a_phone_cannot_reach_it():
    link = pl.phone_link("127.0.0.1", 8000, False, detect=lan)
    assert link.urls == []
    assert "127.0.0.1 only" in link.notes[0] and "--host 0.0.0.0" in link.notes[0]
    assert pl.phone_link("localhost", 8000, True, detect=lan).urls == []
    # A server bound to one LAN address is reached there alone.
    assert pl.phone_link("198.51.100.4", 80, False, detect=lan).urls == ["http://198.51.100.4:80/"]


def test_a_server_in_a_container_asks_for_the_hosts_address():
    """Its own addresses are the container's: the note says how to name the host's, and goes
    once it is named."""
    link = pl.phone_link("0.0.0.0", 8443, True, detect=lan, contained=lambda: True)
    assert "DRONESIM_PHONE_HOSTS" in link.notes[0]
    named = pl.phone_link("0.0.0.0", 8443, True, ["192.168.1.20"], lan, contained=lambda: True)
    assert named.urls[0] == "https://192.168.1.20:8443/"
    assert not any("container" in n for n in named.notes)


def test_no_lan_address_says_so():
    link = pl.phone_link("0.0.0.0", 8000, True, detect=lambda: [])
    assert link.urls == [] and "no LAN address" in link.notes[0]


def test_the_qr_codes_carry_the_url():
    url = "https://192.0.2.7:8443/"
    png = cv2.imdecode(np.frombuffer(pl.qr_png(url), np.uint8), cv2.IMREAD_GRAYSCALE)
    assert decode_qr(png) == url
    assert decode_terminal_qr(pl.qr_text(url).splitlines()) == url
    svg = pl.qr_svg(url).decode()
    # Sized by its viewBox alone, so the page scales it.
    assert re.match(r"<svg [^>]*viewBox=", svg) and not re.match(r"<svg [^>]*\bwidth=", svg)


# ---- the setting --------------------------------------------------------------------------------


def test_phone_hosts_come_comma_separated_from_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("DRONESIM_PHONE_HOSTS", "192.168.1.20, laptop.lan")
    assert load_config().server.phone_hosts == ["192.168.1.20", "laptop.lan"]
    monkeypatch.setenv("DRONESIM_PHONE_HOSTS", "https://192.168.1.20:8443")
    with pytest.raises(ConfigError, match="phone_hosts"):
        load_config()


# ---- serve --------------------------------------------------------------------------------------


def test_serve_with_tls_prints_the_phone_url_and_its_qr_code_and_serves_that_certificate(
    tmp_path,
):
    """A real ``serve --tls`` on loopback: it prints the phone URL (the host named with
    --phone-host first), that the phone must accept the certificate, and a QR code that decodes
    to the URL; the certificate it serves names that host and this machine's LAN addresses."""
    port = free_port()
    env = {k: v for k, v in os.environ.items() if not k.upper().startswith("DRONESIM_")}
    env.update(DRONESIM_ALLOCATOR="system", PYTHONIOENCODING="utf-8", COLUMNS="100")
    command = [sys.executable, "-m", "server", "serve", "--tls", "--no-demo", "--port", str(port)]
    command += ["--data-dir", str(tmp_path / "data"), "--phone-host", "phone-test.invalid"]
    proc = subprocess.Popen(
        command, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    )
    try:
        lines: list[str] = []
        assert proc.stdout is not None
        # Up to the rule that ends the section under the rule titled "phone".
        while not (any(set(x) == {"─", " ", *"phone"} for x in lines) and set(lines[-1]) == {"─"}):
            line = proc.stdout.readline()
            assert line, "serve ended before printing the phone link:\n" + "\n".join(lines)
            lines.append(line.rstrip("\n"))
        text = "\n".join(lines)
        url = f"https://phone-test.invalid:{port}/"
        assert f"open on a phone on the same network: {url}" in text
        assert "accept it once" in text
        code = [line for line in lines if line and set(line) <= set("▀▄█ ")]
        assert decode_terminal_qr(code) == url

        deadline = time.monotonic() + 60
        while True:
            try:
                pem = ssl.get_server_certificate(("127.0.0.1", port), timeout=2).encode()
                break
            except OSError:
                assert proc.poll() is None and time.monotonic() < deadline, "no TLS server"
                time.sleep(0.2)
        served = names_in(pem)
        assert {"phone-test.invalid", "127.0.0.1", "localhost"} | interface_addresses() <= served
    finally:
        proc.kill()
        proc.wait(30)
