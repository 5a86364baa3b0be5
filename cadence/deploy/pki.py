"""The cell's own certificate authority (DESIGN §11: mTLS at the router). Every account of the bus gets a
certificate whose common name is its username, so the router's ACL can name it by ``cert_common_names``
as well as by ``usernames``: a stolen password alone, or a certificate alone, is not enough.

EC P-256 keys (small, fast, accepted by rustls); certificates carry the extensions webpki insists on
(SAN, key usage, extended key usage), since Zenoh verifies them with rustls, not OpenSSL.
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import json
import secrets
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from common.runtime.errors import InputError

T = TypeVar("T")
VALID_DAYS = 3650  # a cell runs for years; to renew, remove credentials/ and install again (new CA)


@dataclass(frozen=True, slots=True)
class Pem:
    """A certificate and its private key, PEM-encoded, as Zenoh's TLS config reads them from files."""

    cert: bytes
    key: bytes


def _key_pem(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )


def _name(cn: str, cell: str) -> x509.Name:
    return x509.Name(
        [
            x509.NameAttribute(NameOID.ORGANIZATION_NAME, f"cadence {cell}"),
            x509.NameAttribute(NameOID.COMMON_NAME, cn),
        ]
    )


def _key_usage(ca: bool) -> x509.KeyUsage:
    """A CA signs certificates; a leaf signs TLS handshakes (EC keys do not encipher)."""
    return x509.KeyUsage(
        digital_signature=not ca,
        content_commitment=False,
        key_encipherment=False,
        data_encipherment=False,
        key_agreement=False,
        key_cert_sign=ca,
        crl_sign=ca,
        encipher_only=False,
        decipher_only=False,
    )


def make_ca(cell: str, now: dt.datetime | None = None) -> Pem:
    now = now or dt.datetime.now(dt.UTC)
    key = ec.generate_private_key(ec.SECP256R1())
    name = _name(f"cadence {cell} CA", cell)
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(now + dt.timedelta(days=VALID_DAYS))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(_key_usage(ca=True), critical=True)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )
    return Pem(cert.public_bytes(serialization.Encoding.PEM), _key_pem(key))


def _san(names: list[str]) -> list[x509.GeneralName]:
    out: list[x509.GeneralName] = []
    for n in names:
        try:
            out.append(x509.IPAddress(ipaddress.ip_address(n)))
        except ValueError:
            out.append(x509.DNSName(n))
    return out


def load_ca(ca: Pem) -> tuple[x509.Certificate, ec.EllipticCurvePrivateKey]:
    """The CA's certificate and key; ``ValueError`` saying what is wrong with them."""
    cert = x509.load_pem_x509_certificate(ca.cert)
    key = serialization.load_pem_private_key(ca.key, password=None)
    if not isinstance(key, ec.EllipticCurvePrivateKey) or key.public_key() != cert.public_key():
        raise ValueError("the CA key is not the CA certificate's (EC) key")
    return cert, key


def issue(ca: Pem, cn: str, cell: str, hosts: list[str], now: dt.datetime | None = None) -> Pem:
    """A leaf certificate for account ``cn``, good as a server (the router, on ``hosts``) and as a client."""
    now = now or dt.datetime.now(dt.UTC)
    ca_cert, ca_key = load_ca(ca)
    key = ec.generate_private_key(ec.SECP256R1())
    cert = (
        x509.CertificateBuilder()
        .subject_name(_name(cn, cell))
        .issuer_name(ca_cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(now + dt.timedelta(days=VALID_DAYS))
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(_key_usage(ca=False), critical=True)
        .add_extension(
            x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
            critical=False,
        )
        .add_extension(x509.SubjectAlternativeName(_san(hosts or [cn])), critical=False)
        .add_extension(
            x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False
        )
        .sign(ca_key, hashes.SHA256())
    )
    return Pem(cert.public_bytes(serialization.Encoding.PEM), _key_pem(key))


def common_name(cert_pem: bytes) -> str:
    cert = x509.load_pem_x509_certificate(cert_pem)
    return str(cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value)


def new_password() -> str:
    return secrets.token_urlsafe(24)


def read_secrets(path: Path, what: str, parse: Callable[[Any], T], error: type[InputError] = InputError) -> T:
    """A JSON file of secrets (a cell's bundle, a plant's secret, its plant.json), ``parse``d; a file that
    cannot be read or is not ``what`` is one line naming it, never a traceback."""
    try:
        return parse(json.loads(path.read_text()))
    except OSError as exc:
        raise error(f"{path}: (file): {exc.strerror or exc}") from exc
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise error(f"{path}: not {what} ({exc!r})") from exc
