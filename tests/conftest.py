"""Shared fixtures: seeded generators and per-test loopback addresses; the cell tests' xdist group."""

from __future__ import annotations

import itertools
import os
import zlib

import numpy as np
import pytest

# Each test that needs the network takes its own 127.0.X.N, so fixed ports
# (RTDE 30004, dashboard 29999) never collide. Each process that runs tests
# takes one block X in 1..200 (250 addresses), clear of 127.0.0.1 and the
# demo's 127.0.0.2: an xdist worker the block after its run's base plus its
# worker number (gw0, gw1, ...), so a run's workers never share one; a run
# without workers the base itself. The base comes from the run's id (the
# same in every worker of a run) or the process id, so parallel runs stay
# apart too.
_BLOCKS = 200
_PER_BLOCK = 250


def _block() -> int:
    worker = os.environ.get("PYTEST_XDIST_WORKER", "")
    run = os.environ.get("PYTEST_XDIST_TESTRUNUID", "")
    base = zlib.crc32(run.encode()) if run else os.getpid()
    index = int(worker[2:]) if worker.startswith("gw") and worker[2:].isdigit() else 0
    return 1 + (base + index) % _BLOCKS


_BLOCK = _block()
_hosts = itertools.count()


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Every test that starts a simulated cell goes to one xdist worker (``--dist loadgroup``): a cell is a
    robot simulator, a daemon and its motion and camera processes, and two of them would fight over two cores."""
    for item in items:
        if item.get_closest_marker("cell") is not None:
            item.add_marker(pytest.mark.xdist_group("cell"))


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(0)


def _next_host() -> str:
    """A loopback address of this process's block not handed out before (they wrap after 250)."""
    return f"127.0.{_BLOCK}.{next(_hosts) % _PER_BLOCK + 2}"


@pytest.fixture
def loopback_host() -> str:
    return _next_host()


@pytest.fixture
def loopback_host2() -> str:
    """A second address of this test's own, for a second simulated robot."""
    return _next_host()


@pytest.fixture(scope="module")
def module_loopback_host() -> str:
    """An address of this module's own, for a fixture its tests share (a simulated cell)."""
    return _next_host()


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


@pytest.fixture
def small_disk(tmp_path):
    """Factory: a tmpfs of ``size`` bytes mounted at a fresh directory, unmounted after the test.

    Skips the test, with the reason, where mounting is not permitted (not
    root, a container without CAP_SYS_ADMIN); the injected-error tests cover
    the same paths there.
    """
    import subprocess

    mounted: list = []

    def make(size: int, name: str = "disk"):
        where = tmp_path / name
        where.mkdir()
        r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size},mode=0700", "tmpfs", str(where)], capture_output=True, text=True)
        if r.returncode != 0:
            pytest.skip(f"cannot mount a tmpfs here (needs root or CAP_SYS_ADMIN): {r.stderr.strip() or r.returncode}")
        mounted.append(where)
        return where

    yield make
    for where in reversed(mounted):
        if subprocess.run(["umount", str(where)], capture_output=True).returncode != 0:
            subprocess.run(["umount", "-l", str(where)], capture_output=True)


def fill_disk(directory, leave: int = 0):
    """Write a filler file into ``directory`` until at most ``leave`` bytes stay free; returns its path."""
    path = os.path.join(directory, "filler")
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    try:
        block = b"\0" * 4096
        while True:
            st = os.statvfs(directory)
            free = st.f_bavail * st.f_frsize
            if free <= leave:
                break
            try:
                os.write(fd, block[: max(1, min(len(block), free - leave))])
            except OSError:
                break
    finally:
        os.close(fd)
    return path
