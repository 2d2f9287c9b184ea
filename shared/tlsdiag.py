"""Why a TLS connection to a router failed: this side's certificate, the CA, or the name.

zenoh reports a refused TLS client only as "Unable to connect to any of [tls/...]". When that
happens :func:`diagnose` looks for the reason itself:

1. the PEM files (``cryptography``): the CA file loads and is in its validity period; this
   side's certificate is in its validity period, was issued by that CA (issuer name and
   signature), and matches its private key;
2. a handshake of its own (Python ``ssl``, the same CA, certificate and key) with the endpoint,
   whose error says whether the router's certificate is not from the CA, has expired, or does not
   name the host dialled, or whether the router refused this side's certificate.

Each finding names the file and the field. Nothing here is on a hot path: it runs once, after a
failed connect.

Example::

    try:
        session = open_session(cfg)
    except ConnectionError as exc:
        print(exc)  # "... certificate: console.pem expired on 2026-01-01 ..."
"""

from __future__ import annotations

import datetime as dt
import socket
import ssl
from dataclasses import dataclass
from pathlib import Path

TIMEOUT_S = 2.0  # the diagnostic handshake's connect and read timeout


@dataclass(frozen=True)
class TlsFiles:
    """The PEM files of one TLS client."""

    ca: str  # CA certificate that verifies the router
    cert: str = ""  # this side's certificate (mutual TLS), "" = none
    key: str = ""  # its private key


def check_files(files: TlsFiles, now: dt.datetime | None = None) -> list[str]:
    """Problems with the PEM files themselves (empty: none found)."""
    from cryptography import x509
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric import ec, padding, rsa

    now = now or dt.datetime.now(dt.UTC)
    out: list[str] = []
    try:
        ca = x509.load_pem_x509_certificate(Path(files.ca).read_bytes())
    except (OSError, ValueError) as exc:
        return [f"CA: {files.ca} is not a PEM certificate ({exc})"]
    if not ca.not_valid_before_utc <= now <= ca.not_valid_after_utc:
        span = f"{ca.not_valid_before_utc:%Y-%m-%d} to {ca.not_valid_after_utc:%Y-%m-%d}"
        out.append(f"CA: {files.ca} is valid {span} only")
    if not files.cert:
        return out
    try:
        cert = x509.load_pem_x509_certificate(Path(files.cert).read_bytes())
    except (OSError, ValueError) as exc:
        return [*out, f"certificate: {files.cert} is not a PEM certificate ({exc})"]
    if now > cert.not_valid_after_utc:
        out.append(f"certificate: {files.cert} expired on {cert.not_valid_after_utc:%Y-%m-%d %H:%M} UTC")
    elif now < cert.not_valid_before_utc:
        start = f"{cert.not_valid_before_utc:%Y-%m-%d %H:%M}"
        out.append(f"certificate: {files.cert} is not valid before {start} UTC")
    if cert.issuer != ca.subject:
        out.append(
            f"CA: {files.cert} was issued by {cert.issuer.rfc4514_string()!r}, "
            f"not by the CA in {files.ca} ({ca.subject.rfc4514_string()!r})"
        )
    else:
        pub = ca.public_key()
        try:
            if isinstance(pub, ec.EllipticCurvePublicKey):
                assert cert.signature_hash_algorithm is not None
                pub.verify(
                    cert.signature, cert.tbs_certificate_bytes, ec.ECDSA(cert.signature_hash_algorithm)
                )
            elif isinstance(pub, rsa.RSAPublicKey):
                assert cert.signature_hash_algorithm is not None
                pub.verify(
                    cert.signature,
                    cert.tbs_certificate_bytes,
                    padding.PKCS1v15(),
                    cert.signature_hash_algorithm,
                )
        except Exception:
            out.append(f"CA: {files.cert} names {files.ca}'s CA as issuer but its signature does not verify")
    if files.key:
        try:
            key = serialization.load_pem_private_key(Path(files.key).read_bytes(), password=None)
            der = serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo
            if key.public_key().public_bytes(*der) != cert.public_key().public_bytes(*der):
                out.append(f"certificate: {files.key} is not the private key of {files.cert}")
        except (OSError, ValueError, TypeError) as exc:
            out.append(f"certificate: {files.key} is not a usable private key ({exc})")
    return out


def handshake(host: str, port: int, files: TlsFiles, server_name: str | None = None) -> str:
    """A TLS handshake of our own with ``host:port``; ``""`` if it succeeds, else the reason,
    starting with ``certificate:``, ``CA:``, ``name:`` or ``connect:``."""
    ctx = ssl.create_default_context(ssl.Purpose.SERVER_AUTH, cafile=files.ca)
    if files.cert:
        ctx.load_cert_chain(files.cert, files.key or None)
    name = server_name or host
    try:
        with (
            socket.create_connection((host, port), timeout=TIMEOUT_S) as raw,
            ctx.wrap_socket(raw, server_hostname=name) as tls,
        ):
            # TLS 1.3: the router judges our certificate after the handshake; a refusal
            # arrives as an alert on the first read
            tls.settimeout(0.3)
            try:
                tls.recv(1)
            except TimeoutError:
                pass
            except ssl.SSLError as exc:
                return _classify(exc, name)
    except ssl.SSLCertVerificationError as exc:
        return _classify(exc, name)
    except ssl.SSLError as exc:
        return _classify(exc, name)
    except OSError as exc:
        return f"connect: {host}:{port}: {exc.strerror or exc}"
    return ""


def _classify(exc: ssl.SSLError, name: str) -> str:
    text = str(getattr(exc, "verify_message", "") or exc.reason or exc)
    low = f"{text} {exc}".lower()
    if isinstance(exc, ssl.SSLCertVerificationError):
        if "hostname" in low or "ip address mismatch" in low:
            return f"name: the router's certificate does not name {name!r} ({text})"
        if "expired" in low or "not yet valid" in low:
            return f"CA: the router's certificate is out of its validity period ({text})"
        return f"CA: the router's certificate is not from the trusted CA ({text})"
    if "certificate required" in low:
        return "certificate: the router requires a client certificate (mutual TLS; --tls-cert/--tls-key)"
    if "unknown ca" in low or "bad certificate" in low or "certificate unknown" in low:
        return f"certificate: the router refused this side's certificate: not from its CA ({text})"
    if "expired" in low:
        return f"certificate: the router refused this side's certificate as expired ({text})"
    return f"TLS: {text}"


def diagnose(endpoint: str, files: TlsFiles) -> str:
    """Every problem found for a failed connect to ``tls/host:port`` (files, then handshake)."""
    address = endpoint.partition("/")[2].partition("#")[0].partition("?")[0]
    host, _, port = address.rpartition(":")
    host = host.strip("[]")
    problems = check_files(files)
    if not problems and port.isdigit() and (reason := handshake(host, int(port), files)):
        problems.append(reason)
    return "; ".join(problems)
