"""The install: constraints.txt pins every dependency pyproject.toml names, at a version its range admits."""

from __future__ import annotations

import tomllib
from pathlib import Path

from packaging.requirements import Requirement
from packaging.utils import canonicalize_name
from packaging.version import Version

ROOT = Path(__file__).resolve().parents[1]


def _pins() -> dict[str, Version]:
    pins: dict[str, Version] = {}
    for n, line in enumerate((ROOT / "constraints.txt").read_text().splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        name, sep, version = line.partition("==")
        assert sep and name and version, f"constraints.txt:{n}: expected NAME==VERSION, got {line!r}"
        key = canonicalize_name(name)
        assert key not in pins, f"constraints.txt:{n}: {name} pinned twice"
        pins[key] = Version(version)
    return pins


def test_every_dependency_of_the_install_is_pinned_within_its_range() -> None:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    # What ./run.sh installs: the runtime dependencies and the test extra (the bench extra is optional).
    wanted = [Requirement(r) for r in [*project["dependencies"], *project["optional-dependencies"]["test"]]]
    pins = _pins()
    missing = [str(r) for r in wanted if canonicalize_name(r.name) not in pins]
    assert not missing, f"constraints.txt pins none of {missing}"
    outside = [
        f"{r.name}=={pins[canonicalize_name(r.name)]} (pyproject.toml: {r})"
        for r in wanted
        if pins[canonicalize_name(r.name)] not in r.specifier
    ]
    assert not outside, f"constraints.txt pins versions pyproject.toml refuses: {outside}"


def test_the_set_up_installs_against_the_constraints() -> None:
    script = (ROOT / "run.sh").read_text()
    assert "-c constraints.txt" in script and "-nt constraints.txt" in script
