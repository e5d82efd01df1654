"""TLS for the Zenoh links: a private certificate authority in the auth directory, a server
certificate for the controller (or router), and the Zenoh settings that use them.

User/password authentication (controller/auth.py) checks only the side that dials, and the
traffic is not encrypted. With TLS (`dobtune auth init DIR --tls HOST ...`, then `tls/`
endpoints) the traffic is encrypted and every client checks that the controller presents a
certificate of DIR's authority for the address it dialled: a rogue peer at that address
cannot pass for the controller (tests/integration/test_tls.py).

Files in DIR: `tls-ca.pem` (the authority's certificate: every client needs it),
`tls-ca-key.pem` (its key: keep it, mode 0600, to issue more certificates), `tls-server.pem` and
`tls-server-key.pem` (the controller's certificate for the HOSTs named: names and IP addresses).
"""

from __future__ import annotations

import datetime
import ipaddress
import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

__all__ = ["CA_FILE", "SERVER_CERT", "SERVER_KEY", "client_tls", "make_tls", "server_tls"]

CA_FILE = "tls-ca.pem"
CA_KEY = "tls-ca-key.pem"
SERVER_CERT = "tls-server.pem"
SERVER_KEY = "tls-server-key.pem"


def _write(path: Path, data: bytes, private: bool) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600 if private else 0o644)
    with os.fdopen(fd, "wb") as f:
        f.write(data)


def make_tls(directory: Path, hosts: Sequence[str], days: int = 825) -> Path:
    """Create the authority and the server certificate for `hosts` in `directory`; returns the
    authority's certificate. ValueError for no host or a bad one."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    if not hosts:
        raise ValueError("--tls: name at least one host (address or name) of the controller")
    sans: list[x509.GeneralName] = []
    for h in hosts:
        try:
            sans.append(x509.IPAddress(ipaddress.ip_address(h)))
        except ValueError:
            if not h or any(c in h for c in "/: "):
                raise ValueError(f"--tls: {h!r} is not a host name or an IP address") from None
            sans.append(x509.DNSName(h))
    now = datetime.datetime.now(datetime.UTC)
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "dobtune authority")])
    ca = (
        x509.CertificateBuilder().subject_name(ca_name).issuer_name(ca_name)
        .public_key(ca_key.public_key()).serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(x509.KeyUsage(
            digital_signature=True, key_cert_sign=True, crl_sign=True, content_commitment=False,
            key_encipherment=False, data_encipherment=False, key_agreement=False,
            encipher_only=False, decipher_only=False), critical=True)
        .sign(ca_key, hashes.SHA256())
    )
    key = ec.generate_private_key(ec.SECP256R1())
    cert = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, hosts[0])]))
        .issuer_name(ca_name).public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=days))
        .add_extension(x509.SubjectAlternativeName(sans), critical=False)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .sign(ca_key, hashes.SHA256())
    )
    pem = serialization.Encoding.PEM
    none = serialization.NoEncryption()
    pkcs8 = serialization.PrivateFormat.PKCS8
    directory.mkdir(mode=0o700, parents=True, exist_ok=True)
    _write(directory / CA_FILE, ca.public_bytes(pem), False)
    _write(directory / CA_KEY, ca_key.private_bytes(pem, pkcs8, none), True)
    _write(directory / SERVER_CERT, cert.public_bytes(pem), False)
    _write(directory / SERVER_KEY, key.private_bytes(pem, pkcs8, none), True)
    return directory / CA_FILE


def server_tls(conf: Any, directory: Path) -> None:
    """Listen on `tls/` endpoints with DIR's server certificate (if DIR has one)."""
    cert, key = directory / SERVER_CERT, directory / SERVER_KEY
    if cert.is_file() and key.is_file():
        conf.insert_json5("transport/link/tls/listen_certificate", json.dumps(str(cert.resolve())))
        conf.insert_json5("transport/link/tls/listen_private_key", json.dumps(str(key.resolve())))


def client_tls(conf: Any, directory: Path) -> None:
    """Trust only DIR's authority on `tls/` endpoints (if DIR has one)."""
    ca = directory / CA_FILE
    if ca.is_file():
        conf.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(str(ca.resolve())))
