"""Cloud file headers are checked against the file's size before a reader allocates what they declare."""

from __future__ import annotations

import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from celld.calib.dataset import read_cloud, write_cloud
from celld.cloudfile import MAX_POINTS, check_cloud_file, load_npy
from celld.errors import InputError

FORGED_PLY = (
    b"ply\nformat binary_little_endian 1.0\nelement vertex 500000000\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
    + bytes(120)
)


def test_a_forged_ply_header_is_refused_before_any_allocation(tmp_path: Path) -> None:
    path = tmp_path / "forged.ply"
    path.write_bytes(FORGED_PLY)
    with pytest.raises(InputError, match=r"declares 500000000 points, more than the 50000000"):
        check_cloud_file(path)
    path.write_bytes(FORGED_PLY.replace(b"500000000", b"2000000"))
    with pytest.raises(InputError, match=r"declares 2000000 points \(12 bytes each, 24000000 bytes\) but the file holds 120 bytes"):
        check_cloud_file(path)
    path.write_bytes(FORGED_PLY)
    with pytest.raises(InputError, match="declares 500000000 points"):
        read_cloud(path, "m")


@pytest.mark.process
def test_reading_the_forged_ply_stays_small_in_a_capped_process(tmp_path: Path) -> None:
    # The defect: Open3D allocated the 5e8 declared points (24 GB). Under a
    # 3 GB address-space cap the reader must refuse, not die.
    path = tmp_path / "forged.ply"
    path.write_bytes(FORGED_PLY)
    code = (
        "import resource, sys\n"
        "from celld.calib.dataset import read_cloud\n"
        "from celld.errors import InputError\n"
        f"resource.setrlimit(resource.RLIMIT_AS, ({3 << 30}, {3 << 30}))\n"
        "try:\n"
        f"    read_cloud({str(path)!r}, 'm')\n"
        "except InputError as exc:\n"
        "    print('refused:', exc)\n"
        "    sys.exit(0)\n"
        "sys.exit(1)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and "refused" in out.stdout, out.stdout + out.stderr


def test_truncated_ascii_and_pcd_headers_are_refused(tmp_path: Path) -> None:
    ascii_ply = tmp_path / "a.ply"
    ascii_ply.write_bytes(
        b"ply\nformat ascii 1.0\nelement vertex 1000\nproperty float x\nproperty float y\nproperty float z\nend_header\n0 0 0\n"
    )
    with pytest.raises(InputError, match="at least 6 characters each"):
        check_cloud_file(ascii_ply)
    pcd = tmp_path / "c.pcd"
    pcd.write_bytes(
        b"VERSION .7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 100000\nHEIGHT 1\nPOINTS 100000\nDATA binary\n" + bytes(12)
    )
    with pytest.raises(InputError, match="declares 100000 points"):
        check_cloud_file(pcd)
    huge = tmp_path / "h.pcd"
    huge.write_bytes(
        f"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {MAX_POINTS + 1}\nHEIGHT 1\nDATA binary_compressed\n".encode()
    )
    with pytest.raises(InputError, match="more than the"):
        check_cloud_file(huge)
    with pytest.raises(InputError, match="expected a .ply or .pcd"):
        (tmp_path / "x.xyz").write_text("0 0 0\n")
        check_cloud_file(tmp_path / "x.xyz")


def test_good_clouds_pass_and_read(tmp_path: Path, rng: np.random.Generator) -> None:
    P = rng.normal(size=(500, 3))
    write_cloud(tmp_path / "c.ply", P)
    assert check_cloud_file(tmp_path / "c.ply") == 500
    np.testing.assert_allclose(read_cloud(tmp_path / "c.ply", "m"), P, atol=1e-6)


def _npy_with_header(path: Path, header: str) -> Path:
    """A .npy file whose header says ``header`` over a few bytes of data."""
    text = header.encode("latin1")
    text += b" " * (118 - len(text)) + b"\n"
    path.write_bytes(b"\x93NUMPY\x01\x00" + struct.pack("<H", len(text)) + text + b"\0" * 64)
    return path


def test_a_npy_header_bomb_is_refused_before_any_allocation(tmp_path: Path) -> None:
    bomb = _npy_with_header(tmp_path / "bomb.npy", "{'descr': '<f8', 'fortran_order': False, 'shape': (100000000000, 3), }")
    with pytest.raises(InputError, match="declares 300000000000 values"):
        load_npy(bomb)
    # Under the cap but more than the file holds.
    short = _npy_with_header(tmp_path / "short.npy", "{'descr': '<f8', 'fortran_order': False, 'shape': (1000, 3), }")
    with pytest.raises(InputError, match="the file holds 64"):
        load_npy(short)
    objects = _npy_with_header(tmp_path / "objects.npy", "{'descr': '|O', 'fortran_order': False, 'shape': (2,), }")
    with pytest.raises(InputError, match="array of numbers"):
        load_npy(objects)
    (tmp_path / "text.npy").write_text("not an array")
    with pytest.raises(InputError, match="not a readable .npy array"):
        load_npy(tmp_path / "text.npy")


@pytest.mark.process
def test_calib_detect_refuses_a_npy_header_bomb_with_a_clear_error(tmp_path: Path) -> None:
    bomb = _npy_with_header(tmp_path / "bomb.npy", "{'descr': '<f8', 'fortran_order': False, 'shape': (100000000000, 3), }")
    got = subprocess.run(
        [sys.executable, "-m", "celld.cli", "calib", "detect", "--flange", "ur10e", "--units", "m", str(bomb)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert got.returncode == 2 and "declares 300000000000 values" in got.stderr and "Traceback" not in got.stderr, got.stderr


def test_a_good_npy_reads_back(tmp_path: Path, rng: np.random.Generator) -> None:
    P = rng.normal(size=(40, 30, 3))
    np.save(tmp_path / "cloud.npy", P)
    np.testing.assert_array_equal(load_npy(tmp_path / "cloud.npy"), P)
