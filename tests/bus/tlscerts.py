"""Test certificates made with the openssl command (the venv has no ``cryptography``): a CA and leaves signed by it."""

from __future__ import annotations

import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

import pytest

# Days the test certificates are valid.
_DAYS = 2


def _openssl(*args: str) -> None:
    r = subprocess.run(["openssl", *args], capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"openssl {' '.join(args[:2])} failed: {r.stderr.strip()}")


def _key(path: Path) -> None:
    _openssl("genpkey", "-algorithm", "EC", "-pkeyopt", "ec_paramgen_curve:P-256", "-out", str(path))
    path.chmod(0o600)


@dataclass(frozen=True)
class Leaf:
    cert: Path
    key: Path


@dataclass(frozen=True)
class CertAuthority:
    """A certificate authority in ``directory``; :meth:`issue` signs leaf certificates."""

    directory: Path
    cert: Path
    key: Path

    @classmethod
    def make(cls, directory: Path, name: str = "celld-test-ca") -> CertAuthority:
        if shutil.which("openssl") is None:
            pytest.skip("the openssl command is not installed")
        directory.mkdir(parents=True, exist_ok=True)
        key, cert = directory / f"{name}.key", directory / f"{name}.pem"
        _key(key)
        _openssl(
            "req",
            "-x509",
            "-new",
            "-key",
            str(key),
            "-out",
            str(cert),
            "-days",
            str(_DAYS),
            "-subj",
            f"/CN={name}",
            "-addext",
            "basicConstraints=critical,CA:TRUE",
            "-addext",
            "keyUsage=critical,keyCertSign,cRLSign",
        )
        return cls(directory, cert, key)

    def issue(self, name: str, ip: str | None = None) -> Leaf:
        """A leaf certificate for ``name`` (common name), for server and client use, naming ``ip`` if given."""
        key, csr, cert = (self.directory / f"{name}.{ext}" for ext in ("key", "csr", "pem"))
        ext = self.directory / f"{name}.ext"
        sans = [f"DNS:{name}"] + ([f"IP:{ip}"] if ip else [])
        ext.write_text(
            f"subjectAltName={','.join(sans)}\nbasicConstraints=CA:FALSE\n"
            "keyUsage=critical,digitalSignature\nextendedKeyUsage=serverAuth,clientAuth\n"
        )
        _key(key)
        _openssl("req", "-new", "-key", str(key), "-out", str(csr), "-subj", f"/CN={name}")
        _openssl(
            "x509",
            "-req",
            "-in",
            str(csr),
            "-CA",
            str(self.cert),
            "-CAkey",
            str(self.key),
            "-CAcreateserial",
            "-out",
            str(cert),
            "-days",
            str(_DAYS),
            "-extfile",
            str(ext),
        )
        return Leaf(cert, key)
