"""The slave site's own services authenticate to the router: a local PKI made at every start.

With a secured router (``telesurg up --acl FILE``, which ``deploy/slave-site.sh`` passes), the
router's listener for this machine's services is no longer plain TCP, open to every local
process: it is mutual TLS on loopback, with its own certificate authority, made here each time
the site starts:

* ``local-ca.pem`` — the local CA; its private key is never written (it signs the certificates
  below in memory and is dropped), so nobody can mint another local identity afterwards;
* ``router.pem`` / ``router.key`` — the router's certificate for ``127.0.0.1`` / ``localhost``;
* ``site-<service>.pem`` / ``.key`` — one client certificate per service (CN ``site-watchdog``,
  ``site-slave_control``, ``site-mapping``, ``site-mirror``, ``site-master_capture``), plus
  ``site-launcher`` (the launcher's start-up probe) and ``site-operator`` (tools run on the slave
  machine: ``telesurg estop``, ``record``, ``console`` with the ``--tls-*`` flags below).

The CN is the identity the access-control rules (``deploy/slave-site/acl.json5``) name, so each
service may publish only its own keys. The site CA of ``telesurg certs`` (the consoles') is a
different CA: a console certificate is refused on this listener and a local certificate on the
consoles' listener; the site CA must not issue ``site-*`` names (``telesurg certs`` refuses them).

Files go to a per-user state directory (default ``$XDG_STATE_HOME/telesurg/<site>-<port>``, else
``~/.local/state/telesurg/<site>-<port>``), mode 0700; keys 0600; never into the repository.

Example (a tool on the slave machine, site ``lab`` on port 7448)::

    d=~/.local/state/telesurg/lab-7448
    telesurg estop --site lab --connect tls/127.0.0.1:7448 --tls-ca $d/local-ca.pem \\
        --tls-cert $d/site-operator.pem --tls-key $d/site-operator.key --mtls
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from telesurg.shared.errors import ConfigError

#: prefix of every local identity (certificate CN); the site CA must not issue such names
PREFIX = "site-"
#: identities besides the services: the launcher's start-up probe, tools run on the slave machine
EXTRA_IDENTITIES = ("launcher", "operator")
LOCAL_HOSTS = ("127.0.0.1", "localhost")
DAYS = 30  # validity of the local certificates; they are made again at every start


def identity(service: str) -> str:
    """Certificate CN of a local service, e.g. ``site-watchdog``."""
    return PREFIX + service


def default_dir(site: str, port: int) -> Path:
    """``$XDG_STATE_HOME/telesurg/<site>-<port>`` (else ``~/.local/state/...``)."""
    base = os.environ.get("XDG_STATE_HOME") or str(Path.home() / ".local" / "state")
    return Path(base) / "telesurg" / f"{site}-{port}"


@dataclass(frozen=True)
class LocalPki:
    """The files of a local PKI in ``root``."""

    root: Path

    @property
    def ca(self) -> Path:
        """The local CA certificate (the services verify the router with it, and vice versa)."""
        return self.root / "local-ca.pem"

    def cert(self, name: str) -> Path:
        """Certificate of ``name`` (``router`` or a service / extra identity)."""
        return self.root / ("router.pem" if name == "router" else f"{identity(name)}.pem")

    def key(self, name: str) -> Path:
        """Private key of ``name``."""
        return self.cert(name).with_suffix(".key")

    def listen_endpoint(self, host: str, port: int) -> str:
        """The router's local listener: mutual TLS with the local CA (endpoint-level TLS config,
        which zenoh lets override the router's own TLS settings, i.e. the consoles' site CA)."""
        for path in (self.ca, self.cert("router"), self.key("router")):
            if any(c in str(path) for c in ";#?="):
                raise ConfigError(
                    f"local credentials path {path} contains one of ;#?= (zenoh endpoint syntax)"
                )
        params = (
            f"root_ca_certificate_file={self.ca}",
            f"listen_certificate_file={self.cert('router')}",
            f"listen_private_key_file={self.key('router')}",
            "enable_mtls=true",
        )
        return f"tls/{host}:{port}#" + ";".join(params)

    def client_flags(self, name: str) -> list[str]:
        """The bus flags of service ``name`` for the local listener."""
        return [
            "--tls-ca",
            str(self.ca),
            "--tls-cert",
            str(self.cert(name)),
            "--tls-key",
            str(self.key(name)),
            "--mtls",
        ]


def _write(path: Path, data: bytes, secret: bool) -> None:
    tmp = path.with_name(path.name + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600 if secret else 0o644)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
    tmp.replace(path)


def make_local_pki(root: Path, services: Sequence[str]) -> LocalPki:
    """Make a fresh local CA in memory, the router's and one certificate per service (and
    :data:`EXTRA_IDENTITIES`) in ``root``; the CA key is not kept."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    root.mkdir(parents=True, exist_ok=True)
    os.chmod(root, 0o700)
    pki = LocalPki(root)
    now = dt.datetime.now(dt.UTC)
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, f"telesurg local CA {root.name}")])
    ca = (
        x509.CertificateBuilder()
        .subject_name(ca_name)
        .issuer_name(ca_name)
        .public_key(ca_key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(now + dt.timedelta(days=DAYS))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(False, False, False, False, False, True, True, False, False), critical=True
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(ca_key.public_key()), critical=False)
        .sign(ca_key, hashes.SHA256())
    )
    _write(pki.ca, ca.public_bytes(serialization.Encoding.PEM), secret=False)
    for name in ("router", *services, *EXTRA_IDENTITIES):
        key = ec.generate_private_key(ec.SECP256R1())
        cn = "site-router" if name == "router" else identity(name)
        builder = (
            x509.CertificateBuilder()
            .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, cn)]))
            .issuer_name(ca_name)
            .public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - dt.timedelta(minutes=5))
            .not_valid_after(now + dt.timedelta(days=DAYS))
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(
                x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
                critical=False,
            )
            .add_extension(
                x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False
            )
        )
        if name == "router":
            sans: list[x509.GeneralName] = [
                x509.IPAddress(ipaddress.ip_address(LOCAL_HOSTS[0])),
                x509.DNSName(LOCAL_HOSTS[1]),
            ]
            builder = builder.add_extension(x509.SubjectAlternativeName(sans), critical=False)
        cert = builder.sign(ca_key, hashes.SHA256())
        pem = key.private_bytes(
            serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
        )
        _write(pki.key(name), pem, secret=True)
        _write(pki.cert(name), cert.public_bytes(serialization.Encoding.PEM), secret=False)
    return pki
