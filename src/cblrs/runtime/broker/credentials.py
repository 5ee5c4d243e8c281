"""Credentials for the backbones (Mosquitto and NATS): random passwords, their hashes, TLS
certificates, and the per-client folders they are handed out in.

What stays with a server and what goes to a client are kept apart:

* the **server's folder** holds only what the server needs: password *hashes*, its own
  certificate and key, the CA certificate (never a clear password, never a client's key);
* each **client's folder** (``<clients>/<user>/``, mode 0700, files 0600) holds that client's
  password, its certificate and key and the CA certificate: copy it to that client's machine
  and delete it here (it is written once; generating again makes new secrets);
* the **CA's key** goes to a folder of its own (``<out>-ca`` by default), never the server's:
  nothing needs it to run.

Hashes: Mosquitto's ``$7$`` (PBKDF2-SHA512, computed here, no clear password on any command
line) and bcrypt for NATS (which checks ``$2a$``/``$2b$`` hashes itself). The generated
passwords are random 144-bit tokens, so a modest cost protects them as well as a high one
while keeping every connection cheap for the server.
"""

from __future__ import annotations

import base64
import datetime
import hashlib
import ipaddress
import os
import secrets
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

from cblrs.errors import CblrsError

CERTIFICATE_DAYS = 365
"""Validity of generated certificates (CA, server, clients), days from generation."""
PBKDF2_ITERATIONS = 101
"""Mosquitto's own default for ``$7$`` hashes; the generated passwords are random 144-bit
tokens, so the iteration count is not what protects them."""
BCRYPT_COST = 10
"""bcrypt cost of NATS password hashes: each connection costs the server one check (~50 ms
at 10 on one core here), and the random 144-bit passwords need no more."""


class CredentialsError(CblrsError):
    """Credentials could not be generated (a missing optional package, a bad folder)."""


def new_password() -> str:
    """A random password: 18 bytes (144 bits), URL-safe base64."""
    return secrets.token_urlsafe(18)


def write_private(path: Path, text: str | bytes) -> Path:
    """Write ``path`` readable by its owner only (0600), also when it existed before."""
    descriptor = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(descriptor, "wb") as handle:
        handle.write(text.encode() if isinstance(text, str) else text)
    os.chmod(path, 0o600)
    return path


def append_private(path: Path) -> BinaryIO:
    """Open ``path`` for appending, readable by its owner only (0600, also when it existed
    before): a server's log names its users, their addresses and what they were refused."""
    descriptor = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o600)
    os.fchmod(descriptor, 0o600)
    return os.fdopen(descriptor, "ab")


def private_folder(path: Path) -> Path:
    """Create ``path`` (and its parents) and make it 0700."""
    path.mkdir(parents=True, exist_ok=True)
    os.chmod(path, 0o700)
    return path


def mosquitto_hash(password: str, salt: bytes | None = None) -> str:
    """A Mosquitto ``$7$`` password hash (what ``mosquitto_passwd`` writes)."""
    salt = secrets.token_bytes(12) if salt is None else salt
    digest = hashlib.pbkdf2_hmac("sha512", password.encode(), salt, PBKDF2_ITERATIONS)
    return (f"$7${PBKDF2_ITERATIONS}${base64.b64encode(salt).decode()}$"
            f"{base64.b64encode(digest).decode()}")


def bcrypt_hash(password: str, cost: int = BCRYPT_COST) -> str:
    """A bcrypt hash (``$2a$``) as nats-server checks it in its ``authorization`` block.

    Raises:
        CredentialsError: the ``bcrypt`` package is missing.
    """
    try:
        # optional extra: pip install cblrs[nats]
        import bcrypt
    except ImportError:
        raise CredentialsError(
            "NATS password hashes need the bcrypt package: pip install cblrs[nats]."
        ) from None
    return bcrypt.hashpw(password.encode(), bcrypt.gensalt(cost, prefix=b"2a")).decode()


# --------------------------------------------------------------------------- certificates


def _x509() -> Any:
    try:
        # optional extra: pip install cblrs[tls]
        import cryptography  # noqa: F401
    except ImportError:
        raise CredentialsError(
            "TLS certificates need the cryptography package: pip install cblrs[tls]."
        ) from None
    from cryptography import x509

    return x509


@dataclass
class Authority:
    """A certificate authority: its certificate file and its key (kept in memory to sign)."""

    name: str
    certificate_file: Path
    key_file: Path
    certificate: Any
    key: Any


def _name(common_name: str) -> Any:
    x509 = _x509()
    from cryptography.x509.oid import NameOID

    return x509.Name([
        x509.NameAttribute(NameOID.ORGANIZATION_NAME, "cblrs"),
        x509.NameAttribute(NameOID.COMMON_NAME, common_name),
    ])


def _pem_key(key: Any) -> bytes:
    from cryptography.hazmat.primitives import serialization

    return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())


def _pem_certificate(certificate: Any) -> bytes:
    from cryptography.hazmat.primitives import serialization

    return certificate.public_bytes(serialization.Encoding.PEM)


def _validity() -> tuple[datetime.datetime, datetime.datetime]:
    start = datetime.datetime.now(datetime.UTC) - datetime.timedelta(minutes=5)
    return start, start + datetime.timedelta(days=CERTIFICATE_DAYS)


def new_authority(common_name: str, certificate_file: Path, key_directory: Path) -> Authority:
    """A new CA (ECDSA P-256): its certificate to ``certificate_file``, its key to
    ``key_directory`` (made 0700; file 0600)."""
    x509 = _x509()
    from cryptography.hazmat.primitives import hashes
    from cryptography.hazmat.primitives.asymmetric import ec

    key = ec.generate_private_key(ec.SECP256R1())
    name = _name(common_name)
    start, until = _validity()
    certificate = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(start)
        .not_valid_after(until)
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True, content_commitment=False, key_encipherment=False,
                data_encipherment=False, key_agreement=False, key_cert_sign=True,
                crl_sign=True, encipher_only=False, decipher_only=False,
            ),
            critical=True,
        )
        .sign(key, hashes.SHA256())
    )
    certificate_file.parent.mkdir(parents=True, exist_ok=True)
    certificate_file.write_bytes(_pem_certificate(certificate))
    private_folder(key_directory)
    key_file = write_private(key_directory / f"{certificate_file.stem}.key", _pem_key(key))
    return Authority(common_name, certificate_file, key_file, certificate, key)


def issue_certificate(
    authority: Authority, common_name: str, *, server: bool = False, client: bool = True,
    hosts: Sequence[str] = (),
) -> tuple[bytes, bytes]:
    """``(certificate PEM, key PEM)`` signed by ``authority``.

    Args:
        common_name: the subject's name (a client's user name).
        server: usable by a server (SAN ``localhost``, ``127.0.0.1`` and ``hosts``).
        client: usable by a client (a node of a NATS cluster is both to its peers).
        hosts: host names or addresses the server is reached at.
    """
    x509 = _x509()
    from cryptography.hazmat.primitives import hashes
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID

    key = ec.generate_private_key(ec.SECP256R1())
    start, until = _validity()
    usages = ([ExtendedKeyUsageOID.SERVER_AUTH] if server else []) + (
        [ExtendedKeyUsageOID.CLIENT_AUTH] if client else [])
    builder = (
        x509.CertificateBuilder()
        .subject_name(_name(common_name))
        .issuer_name(authority.certificate.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(start)
        .not_valid_after(until)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(x509.ExtendedKeyUsage(usages), critical=False)
    )
    if server:
        alternative: list[Any] = [x509.DNSName("localhost"),
                                  x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]
        for host in hosts:
            try:
                address = ipaddress.ip_address(host)
                if str(address) not in ("127.0.0.1", "0.0.0.0", "::"):
                    alternative.append(x509.IPAddress(address))
            except ValueError:
                if host != "localhost":
                    alternative.append(x509.DNSName(host))
        builder = builder.add_extension(x509.SubjectAlternativeName(alternative), critical=False)
    certificate = builder.sign(authority.key, hashes.SHA256())
    return _pem_certificate(certificate), _pem_key(key)


# --------------------------------------------------------------------------- client folders


@dataclass(frozen=True)
class ClientFiles:
    """What one client gets, in its own folder (copy the folder to that client only).

    Attributes:
        user: the login.
        directory: the folder (0700).
        password_file: the password (0600), or None (a certificate-only login).
        ca_file: the CA certificate that signed the server's (TLS only).
        cert_file: the client's certificate (TLS only).
        key_file: the client's private key, 0600 (TLS only).
    """

    user: str
    directory: Path
    password_file: Path | None
    ca_file: Path | None = None
    cert_file: Path | None = None
    key_file: Path | None = None

    def password(self) -> str | None:
        """The password, read from its file (None when there is none)."""
        if self.password_file is None:
            return None
        return self.password_file.read_text().strip()

    def to_dict(self) -> dict[str, str | None]:
        return {
            "directory": str(self.directory),
            "password_file": _text(self.password_file),
            "ca_file": _text(self.ca_file),
            "cert_file": _text(self.cert_file),
            "key_file": _text(self.key_file),
        }


def _text(path: Path | None) -> str | None:
    return None if path is None else str(path)


def write_client_folder(
    clients_directory: Path,
    user: str,
    password: str | None,
    authority: Authority | None = None,
) -> ClientFiles:
    """Write ``<clients_directory>/<user>/``: ``<user>.password`` and, with an authority,
    ``ca.crt``, ``<user>.crt`` and ``<user>.key`` (the certificate's common name is the
    user)."""
    private_folder(clients_directory)
    folder = private_folder(clients_directory / user)
    password_file = None
    if password is not None:
        password_file = write_private(folder / f"{user}.password", password + "\n")
    if authority is None:
        return ClientFiles(user, folder, password_file)
    certificate, key = issue_certificate(authority, user)
    ca_file = folder / "ca.crt"
    ca_file.write_bytes(authority.certificate_file.read_bytes())
    cert_file = folder / f"{user}.crt"
    cert_file.write_bytes(certificate)
    key_file = write_private(folder / f"{user}.key", key)
    return ClientFiles(user, folder, password_file, ca_file, cert_file, key_file)


def default_side_folder(directory: Path, suffix: str) -> Path:
    """``<directory>-<suffix>`` beside ``directory`` (the CA's keys, the clients' folders)."""
    return directory.with_name(f"{directory.name}-{suffix}")


def check_outside(folder: Path, directory: Path, what: str) -> Path:
    """``folder`` resolved, or raise if it lies inside ``directory`` (the server's files)."""
    folder = folder.resolve()
    if folder == directory or directory in folder.parents:
        raise CredentialsError(f"the {what} folder {folder} must lie outside {directory}.")
    return folder
