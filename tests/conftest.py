"""Shared fixtures: seeded generators and per-test loopback addresses."""

from __future__ import annotations

import itertools
import os

import numpy as np
import pytest

# Each test that needs the network takes its own 127.0.0.N, so fixed ports
# (RTDE 30004, dashboard 29999) never collide. Start high enough to stay clear
# of 127.0.0.1 and the demo's 127.0.0.2; the pid spreads parallel runs apart.
_hosts = itertools.count(10 + (os.getpid() % 20) * 10)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(0)


@pytest.fixture
def loopback_host() -> str:
    n = next(_hosts)
    return f"127.0.{n // 250}.{n % 250 + 2}"
