"""``telesurg certs``: a certificate authority and one certificate per identity, for mutual TLS.

The slave site's router requires mutual TLS and keys its access-control rules on the
certificate common name (CN), so the CN *is* the identity:

* ``slave-site`` — the router's server certificate (its subject-alternative names must contain
  every name or address a console dials, ``--host``); also usable by slave-site services;
* ``console`` — may publish master streams and the e-stop, and query operator commands;
* ``viewer`` — may only subscribe.

Files written to ``--out`` (default ``certs/``): ``ca.pem`` + ``ca.key`` (keep the CA key off the
machines: it signs new identities), and ``<identity>.pem`` + ``<identity>.key`` for each identity.
Keys are ECDSA P-256, PKCS#8 PEM, mode 0600. Copy ``ca.pem`` and one identity's pair to each
machine. Existing files are kept unless ``--force``; a new identity for an existing CA only
needs ``--identity NAME`` (the CA is reused).

Examples::

    telesurg certs --out certs --host slave.lab.example --host 192.168.1.20
    telesurg certs --out certs --identity console2          # one more console, same CA
    python -m telesurg.services.certs --out /tmp/other --identity console   # an unrelated CA (tests)
"""

from __future__ import annotations

import argparse
import datetime as dt
import ipaddress
import os
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID
from telesurg.shared.errors import ConfigError
from telesurg.shared.keys import check_id

#: The identities the slave site's access-control rules know (deploy/slave-site/acl.json5).
IDENTITIES = ("slave-site", "console", "viewer")
SERVER_IDENTITY = "slave-site"  # the router's certificate: carries the --host names
CA_NAME = "telesurg CA"


@dataclass
class CertsConfig:
    """What ``telesurg certs`` makes."""

    out: Path = Path("certs")  # output directory
    identities: tuple[str, ...] = IDENTITIES  # common names to issue (one certificate each)
    hosts: tuple[str, ...] = ("localhost", "127.0.0.1")  # DNS names / IPs the slave site is dialled by
    days: int = 825  # validity of the identity certificates, days (the CA gets 10 years)
    force: bool = False  # overwrite existing files (a new CA invalidates every issued certificate)
    ca_name: str = CA_NAME  # common name of the CA
    written: list[Path] = field(default_factory=list)  # filled by make_certs

    def validate(self) -> None:
        """Raise ConfigError for an unusable request."""
        if not self.identities:
            raise ConfigError("no identities to issue; e.g. --identity console")
        for ident in self.identities:
            check_id("identity", ident)
            if ident.startswith("site-"):  # services/launcher/lockdown.py: the local services' names
                raise ConfigError(
                    f"identity {ident!r}: site-* names belong to the slave site's local services "
                    "(made by telesurg up at every start), not to the site CA"
                )
        if not 1 <= self.days <= 3650:
            raise ConfigError(f"days={self.days} outside [1, 3650]")
        if not self.hosts and SERVER_IDENTITY in self.identities:
            raise ConfigError("the slave-site certificate needs at least one --host name or address")


def _san(hosts: Sequence[str]) -> list[x509.GeneralName]:
    names: list[x509.GeneralName] = []
    for h in hosts:
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(h)))
        except ValueError:
            names.append(x509.DNSName(h))
    return names


def _write(path: Path, data: bytes, secret: bool) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600 if secret else 0o644)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
    tmp.replace(path)


def _new_key() -> ec.EllipticCurvePrivateKey:
    return ec.generate_private_key(ec.SECP256R1())


def _key_pem(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )


def _load_or_make_ca(cfg: CertsConfig) -> tuple[x509.Certificate, ec.EllipticCurvePrivateKey, bool]:
    """(certificate, key, new) of the CA in ``cfg.out``; made if absent (or ``force``)."""
    ca_pem, ca_key = cfg.out / "ca.pem", cfg.out / "ca.key"
    if ca_pem.exists() and ca_key.exists() and not cfg.force:
        cert = x509.load_pem_x509_certificate(ca_pem.read_bytes())
        key = serialization.load_pem_private_key(ca_key.read_bytes(), password=None)
        if not isinstance(key, ec.EllipticCurvePrivateKey):
            raise ConfigError(f"{ca_key} is not an ECDSA key (made by another tool?); use --force or --out")
        return cert, key, False
    key = _new_key()
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, cfg.ca_name)])
    now = dt.datetime.now(dt.UTC)
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(now + dt.timedelta(days=3650))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                key_cert_sign=True,
                crl_sign=True,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )
    _write(ca_key, _key_pem(key), secret=True)
    _write(ca_pem, cert.public_bytes(serialization.Encoding.PEM), secret=False)
    cfg.written += [ca_pem, ca_key]
    return cert, key, True


def _issue(
    cfg: CertsConfig,
    ca_cert: x509.Certificate,
    ca_key: ec.EllipticCurvePrivateKey,
    ident: str,
    replace: bool,
) -> None:
    pem, key_path = cfg.out / f"{ident}.pem", cfg.out / f"{ident}.key"
    if pem.exists() and key_path.exists() and not replace:
        return
    key = _new_key()
    now = dt.datetime.now(dt.UTC)
    # Every identity may act as TLS client and server (a console machine could host a router);
    # only the slave site's certificate names hosts. Without a SAN, a client certificate is fine:
    # the router authenticates it by the CA and reads its CN for the access-control rules.
    hosts = cfg.hosts if ident == SERVER_IDENTITY else ()
    builder = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, ident)]))
        .issuer_name(ca_cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5))
        .not_valid_after(now + dt.timedelta(days=cfg.days))
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=True,
                key_cert_sign=False,
                crl_sign=False,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(
            x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
            critical=False,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .add_extension(
            x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False
        )
    )
    if hosts:
        builder = builder.add_extension(x509.SubjectAlternativeName(_san(hosts)), critical=False)
    cert = builder.sign(ca_key, hashes.SHA256())
    _write(key_path, _key_pem(key), secret=True)
    _write(pem, cert.public_bytes(serialization.Encoding.PEM), secret=False)
    cfg.written += [pem, key_path]


def make_certs(cfg: CertsConfig) -> list[Path]:
    """Make (or reuse) the CA in ``cfg.out`` and issue each identity; returns the files written.

    Raises:
        ConfigError: bad identity names, days or hosts.
    """
    cfg.validate()
    cfg.written = []
    ca_cert, ca_key, new_ca = _load_or_make_ca(cfg)
    for ident in cfg.identities:  # a new CA re-issues every identity: the old ones no longer verify
        _issue(cfg, ca_cert, ca_key, ident, replace=new_ca or cfg.force)
    return list(cfg.written)


def common_name(pem: Path) -> str:
    """The CN of the certificate in ``pem``."""
    cert = x509.load_pem_x509_certificate(pem.read_bytes())
    return str(cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value)


def main(argv: Sequence[str] | None = None) -> int:
    """``telesurg certs``."""
    ap = argparse.ArgumentParser(
        prog="telesurg certs", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--out", type=Path, default=Path("certs"), help="output directory (default: certs)")
    ap.add_argument(
        "--identity",
        action="append",
        metavar="NAME",
        help=f"common name to issue, repeatable (default: {', '.join(IDENTITIES)})",
    )
    ap.add_argument(
        "--host",
        action="append",
        metavar="NAME_OR_IP",
        help="a name or address consoles dial the slave site by, repeatable "
        "(default: localhost, 127.0.0.1); goes into the slave-site certificate",
    )
    ap.add_argument("--days", type=int, default=825, help="identity certificate validity (default 825)")
    ap.add_argument("--force", action="store_true", help="overwrite existing files (new CA and keys)")
    args = ap.parse_args(argv)
    cfg = CertsConfig(out=args.out, days=args.days, force=args.force)
    if args.identity:
        cfg.identities = tuple(args.identity)
    if args.host:
        cfg.hosts = tuple(args.host)
    try:
        written = make_certs(cfg)
    except ConfigError as exc:
        print(f"telesurg certs: {exc}", file=sys.stderr)
        return 2
    for p in written:
        print(f"wrote {p}")
    kept = [i for i in cfg.identities if cfg.out / f"{i}.pem" not in written]
    if kept:
        print(f"kept existing {', '.join(kept)} in {cfg.out} (--force replaces them)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
