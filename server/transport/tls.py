"""A self-signed certificate for HTTPS on a local network: phone browsers give camera and depth
access only on a secure origin.

The certificate is kept in a folder and used again on later runs, so that a phone asked to
accept it once keeps accepting it. It is made anew only when it no longer serves: expired (or
about to be), unreadable, not matching its key, or not naming an address the server is now
reached by (the laptop joined another network). The new one names the old one's hosts too, so
moving back to an earlier network needs no third certificate."""

from __future__ import annotations

import datetime as dt
import ipaddress
import logging
import socket
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID

from server.atomic import atomic_write_bytes

log = logging.getLogger(__name__)

VALID_DAYS = 825  # the longest validity iOS accepts for a certificate a user trusts
RENEW_BEFORE = dt.timedelta(days=1)  # a certificate this close to its end is made anew
ALWAYS = ("localhost", "127.0.0.1")  # the machine's own browser


@dataclass(frozen=True)
class Certificate:
    """The files uvicorn serves, the hosts the certificate names, and whether this run made it
    (a phone that accepted the previous one must accept this one once more)."""

    cert: Path
    key: Path
    hosts: tuple[str, ...]
    issued: bool


def ensure_certificate(folder: Path, hosts: Iterable[str] = ()) -> Certificate:
    """The certificate in ``folder`` (cert.pem, key.pem), made when missing or when it does not
    name all of ``hosts`` (IP addresses or DNS names, besides localhost, 127.0.0.1 and this
    machine's name, which it always names)."""
    cert_path, key_path = folder / "cert.pem", folder / "key.pem"
    wanted = _normalised([*ALWAYS, socket.gethostname(), *hosts])
    kept = _kept_hosts(cert_path, key_path)
    if kept is not None and wanted <= kept:
        return Certificate(cert_path, key_path, tuple(sorted(kept)), issued=False)
    names = wanted | (kept or set())
    if kept is not None:
        log.warning(
            "TLS certificate %s does not name %s: making a new one",
            cert_path,
            ", ".join(sorted(wanted - kept)),
        )
    _issue(cert_path, key_path, names)
    return Certificate(cert_path, key_path, tuple(sorted(names)), issued=True)


def certificate_hosts(cert_path: Path) -> set[str]:
    """The hosts a certificate names (its subject alternative names), normalised."""
    cert = x509.load_pem_x509_certificate(cert_path.read_bytes())
    alt = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    ips = [str(a) for a in alt.get_values_for_type(x509.IPAddress)]
    return _normalised([*alt.get_values_for_type(x509.DNSName), *ips])


def _kept_hosts(cert_path: Path, key_path: Path) -> set[str] | None:
    """The hosts the kept certificate names; None when there is none that still serves."""
    if not (cert_path.is_file() and key_path.is_file()):
        return None
    try:
        cert = x509.load_pem_x509_certificate(cert_path.read_bytes())
        key = serialization.load_pem_private_key(key_path.read_bytes(), password=None)
        hosts = certificate_hosts(cert_path)
    except (ValueError, TypeError, x509.ExtensionNotFound) as exc:
        log.warning("TLS certificate %s is unreadable (%s): making a new one", cert_path, exc)
        return None
    if cert.public_key() != key.public_key():
        log.warning("TLS certificate %s does not match %s: making a new one", cert_path, key_path)
        return None
    if cert.not_valid_after_utc - RENEW_BEFORE < dt.datetime.now(dt.timezone.utc):
        log.warning(
            "TLS certificate %s expires %s: making a new one",
            cert_path,
            cert.not_valid_after_utc.date(),
        )
        return None
    return hosts


def _normalised(hosts: Iterable[str]) -> set[str]:
    """Addresses in their canonical text, names in lower case: the forms a comparison needs."""
    out = set()
    for host in hosts:
        try:
            out.add(str(ipaddress.ip_address(host)))
        except ValueError:
            out.add(host.lower())
    return out


def _issue(cert_path: Path, key_path: Path, hosts: set[str]) -> None:
    """Write a new key and a certificate naming ``hosts``, signed by that key."""
    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "dronesim-ar local server")])
    alt: list[x509.GeneralName] = []
    for host in sorted(hosts):
        try:
            alt.append(x509.IPAddress(ipaddress.ip_address(host)))
        except ValueError:
            alt.append(x509.DNSName(host))
    now = dt.datetime.now(dt.timezone.utc)
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(days=1))
        .not_valid_after(now + dt.timedelta(days=VALID_DAYS))
        .add_extension(x509.SubjectAlternativeName(alt), critical=False)
        .sign(key, hashes.SHA256())
    )
    atomic_write_bytes(  # owner-only, as atomic_write_bytes makes every file
        key_path,
        key.private_bytes(
            serialization.Encoding.PEM,
            serialization.PrivateFormat.PKCS8,
            serialization.NoEncryption(),
        ),
    )
    atomic_write_bytes(cert_path, cert.public_bytes(serialization.Encoding.PEM))
