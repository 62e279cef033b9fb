"""Shared fixtures: seeded generators and per-test loopback addresses."""

from __future__ import annotations

import itertools
import os

import numpy as np
import pytest

# Each test that needs the network takes its own 127.0.X.N, so fixed ports
# (RTDE 30004, dashboard 29999) never collide. Each run takes the block
# X = 1 + pid % 200 (250 addresses), so parallel runs stay apart and clear of
# 127.0.0.1 and the demo's 127.0.0.2.
_hosts = itertools.count((1 + os.getpid() % 200) * 250)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(0)


@pytest.fixture
def loopback_host() -> str:
    n = next(_hosts)
    return f"127.0.{n // 250}.{n % 250 + 2}"


@pytest.fixture
def sim_robot(loopback_host: str):
    """A simulated UR10e controller process on this test's own loopback address.

    Yields a :class:`celld.sim.robot.SimRobotHandle`; ``sim_robot.host`` is the
    address to give ur-rtde. Disconnect ur-rtde objects before the test ends:
    the simulator stops when the fixture is torn down. It runs at SCHED_FIFO
    where the OS allows it, so that it keeps its 2 ms cycle on a loaded test
    machine as a real controller would (it takes 10-20 % of one core).
    """
    from celld.sim.robot import launch

    with launch(loopback_host, realtime=True) as handle:
        yield handle
