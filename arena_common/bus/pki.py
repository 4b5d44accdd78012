"""The lab's own certificate authority: one CA, one certificate per host of the config (CN = host name).

``arena security init`` calls :func:`init_lab`; :func:`check_certificate` (``arena security check``)
verifies what a host needs before it starts: every file present, private keys and passwords readable by their owner
only, each certificate signed by the lab CA, named after its host and not expired.  Keys are ECDSA P-256,
certificates valid for ``days`` days (default two years) with the host's name, its configured address,
``localhost`` and 127.0.0.1 as subject alternative names (a host's own services reach its router on
loopback too).
"""

from __future__ import annotations

import datetime
import ipaddress
import os
import stat
from collections.abc import Iterable
from pathlib import Path

from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from arena_common.core.errors import ArenaError

__all__ = [
    "PkiError",
    "check_certificate",
    "init_lab",
    "issue_certificate",
    "make_ca",
    "secret_mode_problem",
]


class PkiError(ArenaError):
    """A certificate or key that cannot be made or does not hold (named, with the reason)."""


def _write(path: Path, data: bytes, mode: int) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
    os.chmod(path, mode)  # an existing file keeps its mode through O_CREAT


def _key_pem(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )


def make_ca(directory: Path, name: str, days: int = 3650) -> tuple[Path, Path]:
    """A self-signed CA (``ca.pem``, and ``ca.key`` readable by its owner only) in ``directory``."""
    key = ec.generate_private_key(ec.SECP256R1())
    subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, f"{name} arena CA")])
    now = datetime.datetime.now(datetime.UTC)
    cert = (
        x509.CertificateBuilder()
        .subject_name(subject)
        .issuer_name(subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(False, False, False, False, False, True, True, False, False), critical=True
        )
        .sign(key, hashes.SHA256())
    )
    ca_pem, ca_key = directory / "ca.pem", directory / "ca.key"
    _write(ca_key, _key_pem(key), 0o600)
    _write(ca_pem, cert.public_bytes(serialization.Encoding.PEM), 0o644)
    return ca_pem, ca_key


def _load_ca(ca_pem: Path, ca_key: Path) -> tuple[x509.Certificate, ec.EllipticCurvePrivateKey]:
    cert = x509.load_pem_x509_certificate(ca_pem.read_bytes())
    key = serialization.load_pem_private_key(ca_key.read_bytes(), password=None)
    if not isinstance(key, ec.EllipticCurvePrivateKey):
        raise PkiError(f"{ca_key}: not an EC private key")
    return cert, key


def issue_certificate(
    ca_pem: Path, ca_key: Path, name: str, out: Path, addresses: Iterable[str] = (), days: int = 730
) -> tuple[Path, Path]:
    """``<out>/<name>.pem`` and ``<name>.key``: a certificate for ``name`` (CN and DNS name) signed by the CA."""
    ca_cert, ca_private = _load_ca(ca_pem, ca_key)
    key = ec.generate_private_key(ec.SECP256R1())
    alt: list[x509.GeneralName] = [x509.DNSName(name), x509.DNSName("localhost")]
    ips = {"127.0.0.1", *(a for a in addresses if a)}
    for a in sorted(ips):
        try:
            alt.append(x509.IPAddress(ipaddress.ip_address(a.strip("[]"))))
        except ValueError:
            alt.append(x509.DNSName(a))
    now = datetime.datetime.now(datetime.UTC)
    cert = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)]))
        .issuer_name(ca_cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(x509.SubjectAlternativeName(alt), critical=False)
        .add_extension(
            x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
            critical=False,
        )
        .add_extension(
            x509.KeyUsage(True, False, False, False, False, False, False, False, False), critical=True
        )
        .sign(ca_private, hashes.SHA256())
    )
    pem, key_path = out / f"{name}.pem", out / f"{name}.key"
    _write(key_path, _key_pem(key), 0o600)
    _write(pem, cert.public_bytes(serialization.Encoding.PEM), 0o644)
    return pem, key_path


def secret_mode_problem(path: Path) -> str:
    """Why ``path`` is no safe place for a secret ('' if it is): readable by its group or by others."""
    mode = stat.S_IMODE(path.stat().st_mode)
    if mode & 0o077:
        return f"{path} is readable by others (mode {mode:04o}): chmod 600 {path}"
    return ""


def check_certificate(ca_pem: Path, cert_pem: Path, key_pem: Path, name: str) -> list[str]:
    """Problems of one host's certificate and key (empty: it holds)."""
    problems: list[str] = []
    for p in (ca_pem, cert_pem, key_pem):
        if not p.is_file():
            return [f"{p} does not exist"]
    ca = x509.load_pem_x509_certificate(ca_pem.read_bytes())
    cert = x509.load_pem_x509_certificate(cert_pem.read_bytes())
    cn = [a.value for a in cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)]
    if cn != [name]:
        problems.append(f"{cert_pem}: common name {cn[0] if cn else None!r} is not the host name {name!r}")
    try:
        ca_key = ca.public_key()
        if not isinstance(ca_key, ec.EllipticCurvePublicKey):
            raise PkiError("the lab CA's key is not an EC key")
        cert.verify_directly_issued_by(ca)
    except (ValueError, TypeError, InvalidSignature, PkiError) as exc:
        problems.append(f"{cert_pem}: not signed by the lab CA {ca_pem} ({exc or 'bad signature'})")
    now = datetime.datetime.now(datetime.UTC)
    if not cert.not_valid_before_utc <= now <= cert.not_valid_after_utc:
        problems.append(
            f"{cert_pem}: not valid now (valid {cert.not_valid_before_utc} to {cert.not_valid_after_utc})"
        )
    private = serialization.load_pem_private_key(key_pem.read_bytes(), password=None)
    if private.public_key().public_bytes(
        serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo
    ) != cert.public_key().public_bytes(
        serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo
    ):
        problems.append(f"{key_pem}: is not the key of {cert_pem}")
    if problem := secret_mode_problem(key_pem):
        problems.append(problem)
    return problems


def init_lab(
    directory: Path, arena_name: str, hosts: dict[str, str], names: Iterable[str] = (), *, force: bool = False
) -> dict[str, tuple[Path, Path]]:
    """Make the lab CA and a certificate for every host (``name → address``) and extra identity ``names``:
    each name's ``(certificate, key)``; the CA is ``ca.pem`` beside them.

    Refuses to overwrite an existing CA unless ``force`` (a new CA invalidates every certificate).
    The directory is made readable by its owner only.
    """
    directory.mkdir(parents=True, exist_ok=True)
    os.chmod(directory, 0o700)
    ca_pem, ca_key = directory / "ca.pem", directory / "ca.key"
    if ca_pem.exists() and not force:
        raise PkiError(
            f"{ca_pem} exists: a lab CA is already there (--force makes a new one and new certificates)"
        )
    make_ca(directory, arena_name)
    return {
        name: issue_certificate(ca_pem, ca_key, name, directory, [address])
        for name, address in {**hosts, **{n: "" for n in names}}.items()
    }
