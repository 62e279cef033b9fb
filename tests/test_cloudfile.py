"""Cloud file headers are checked against the file's size before a reader allocates what they declare."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from celld.calib.dataset import read_cloud, write_cloud
from celld.cloudfile import MAX_POINTS, check_cloud_file
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
