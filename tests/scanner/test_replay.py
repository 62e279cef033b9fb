"""Replay of organized clouds from a directory: formats, units, order, and refused files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from celld.errors import DeviceError, InputError
from celld.scanner import Scanner
from celld.scanner.replay import ReplayScanner, read_cloud_file, write_cloud_file


def _cloud(rng: np.random.Generator, h: int = 12, w: int = 16) -> np.ndarray:
    P = np.empty((h, w, 3), dtype=np.float32)
    P[..., 0:2] = rng.uniform(-0.2, 0.2, (h, w, 2))
    P[..., 2] = rng.uniform(0.5, 1.0, (h, w))
    P[0, :3] = np.nan
    return P


def _ply_header(w: int, h: int, fmt: str = "binary_little_endian", props: str = "float x\nproperty float y\nproperty float z") -> str:
    return f"ply\nformat {fmt} 1.0\ncomment width {w}\ncomment height {h}\nelement vertex {w * h}\nproperty {props}\nend_header\n"


@pytest.mark.parametrize("suffix", [".npy", ".ply"])
@pytest.mark.parametrize("units", ["m", "mm"])
def test_written_clouds_read_back_in_metres(tmp_path: Path, rng: np.random.Generator, suffix: str, units: str) -> None:
    P = _cloud(rng)
    path = write_cloud_file(tmp_path / f"0000{suffix}", P, units)
    back = read_cloud_file(path, units)
    np.testing.assert_allclose(back, P, rtol=1e-6, equal_nan=True)
    if units == "mm":
        # The file itself is in millimetres; reading it as metres is 1000 times off.
        np.testing.assert_allclose(read_cloud_file(path, "m")[5, 5, 2], P[5, 5, 2] * 1e3, rtol=1e-6)


def test_an_ascii_ply_with_extra_properties_and_obj_info_grid(tmp_path: Path) -> None:
    path = tmp_path / "scan.ply"
    rows = ["0 0 0 7 10", "1 2 650 7 10", "-1 2 651 7 10", "0 0 0 7 10", "5 6 700 1 1", "5 6 701 1 1"]
    header = (
        "ply\nformat ascii 1.0\nobj_info Width 3\nobj_info Height 2\nelement vertex 6\n"
        "property double x\nproperty double y\nproperty double z\nproperty uchar intensity\nproperty float confidence\n"
        "element face 0\nproperty list uchar int vertex_indices\nend_header\n"
    )
    path.write_text(header + "\n".join(rows) + "\n")
    P = read_cloud_file(path, "mm")
    assert P.shape == (2, 3, 3)
    assert np.isnan(P[0, 0]).all() and np.isnan(P[1, 0]).all()
    np.testing.assert_allclose(P[0, 1], [0.001, 0.002, 0.65], rtol=1e-6)


def test_the_replay_goes_in_file_name_order_and_ends_or_loops(tmp_path: Path, rng: np.random.Generator) -> None:
    clouds = [_cloud(rng) for _ in range(3)]
    for i, P in enumerate(clouds):
        write_cloud_file(tmp_path / f"{i:04d}{'.npy' if i % 2 else '.ply'}", P)
    (tmp_path / "poses.json").write_text("{}")  # not a cloud: left alone
    stamps = iter(range(100, 200))
    scanner = ReplayScanner(tmp_path, clock=lambda: next(stamps))
    assert isinstance(scanner, Scanner)
    assert scanner.info()["files"] == 3 and scanner.info()["width_px"] == 16
    for i, P in enumerate(clouds):
        cloud = scanner.capture()
        np.testing.assert_allclose(cloud.points, P, equal_nan=True)
        assert cloud.stamp_ns == 100 + i
    with pytest.raises(DeviceError, match="all 3 clouds were replayed"):
        scanner.capture()
    health = scanner.health()
    assert health["captures"] == 3 and health["failures"] == 1 and not health["ok"]
    looping = ReplayScanner(tmp_path, loop=True)
    for _ in range(4):
        cloud = looping.capture()
    np.testing.assert_allclose(cloud.points, clouds[0], equal_nan=True)
    looping.close()
    with pytest.raises(DeviceError, match="after close"):
        looping.capture()


def test_missing_or_empty_directories_are_refused(tmp_path: Path) -> None:
    with pytest.raises(DeviceError, match="not a directory"):
        ReplayScanner(tmp_path / "nope")
    with pytest.raises(DeviceError, match="no .npy or .ply clouds"):
        ReplayScanner(tmp_path)
    with pytest.raises(InputError, match="units"):
        ReplayScanner(tmp_path, units="inch")


def _bad_files(tmp_path: Path) -> dict[str, tuple[Path, str]]:
    """One malformed file per case: (path, the reason the refusal must give)."""
    cases: dict[str, tuple[Path, str]] = {}
    p = tmp_path / "flat.npy"
    np.save(p, np.zeros((10, 3), np.float32))
    cases["npy of the wrong shape"] = (p, r"expected an organized \(H, W, 3\) array, got shape \(10, 3\)")
    p = tmp_path / "ints.npy"
    np.save(p, np.zeros((2, 2, 3), np.int32))
    cases["npy of integers"] = (p, "expected float coordinates")
    p = tmp_path / "pickle.npy"
    np.save(p, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    cases["npy with pickled objects"] = (p, "not a readable .npy array")
    p = tmp_path / "junk.ply"
    p.write_bytes(b"hello world")
    cases["not a ply"] = (p, "not a PLY file")
    p = tmp_path / "nogrid.ply"
    p.write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n0 0 1\n")
    cases["ply without grid"] = (p, "needs its grid in the header")
    p = tmp_path / "mismatch.ply"
    p.write_bytes(_ply_header(4, 4).replace("element vertex 16", "element vertex 15").encode() + bytes(15 * 12))
    cases["ply grid mismatch"] = (p, "header grid 4 x 4 does not match its 15 vertices")
    p = tmp_path / "noz.ply"
    p.write_bytes(_ply_header(2, 2, props="float x\nproperty float y").encode() + bytes(4 * 8))
    cases["ply without z"] = (p, "expected vertex properties x, y, z")
    p = tmp_path / "listprop.ply"
    p.write_bytes(_ply_header(2, 2, props="float x\nproperty float y\nproperty float z\nproperty list uchar int n").encode())
    cases["ply with a list property"] = (p, "not a scalar PLY type")
    return cases


def test_each_malformed_file_is_refused_at_open_with_its_name_and_reason(tmp_path: Path) -> None:
    for what, (path, reason) in _bad_files(tmp_path).items():
        one = tmp_path / what.replace(" ", "_")
        one.mkdir()
        path.rename(one / path.name)
        with pytest.raises(InputError, match=reason) as info:
            ReplayScanner(one)
        assert path.name in str(info.value), what


def test_damage_in_the_body_is_found_when_the_file_is_opened_or_read(tmp_path: Path, rng: np.random.Generator) -> None:
    good = write_cloud_file(tmp_path / "0000.ply", _cloud(rng))
    data = good.read_bytes()
    good.write_bytes(data[:-100])  # truncated body, header intact: found from the header and the size
    with pytest.raises(InputError, match=r"0000.ply: the header declares 192 points .* holds 2204 bytes after its header"):
        ReplayScanner(tmp_path)
    inf = _cloud(rng)
    inf[3, 3, 0] = np.inf
    np.save(tmp_path / "0000.npy", inf)
    (tmp_path / "0000.ply").unlink()
    with pytest.raises(InputError, match="0000.npy: 1 pixels hold infinite"):
        ReplayScanner(tmp_path).capture()
    (tmp_path / "0000.npy").unlink()
    ascii_ = tmp_path / "0001.ply"
    ascii_.write_text(_ply_header(2, 2, fmt="ascii") + "0 0 1\n0 0 1\n0 0 1\n0 0 x\n")
    with pytest.raises(InputError, match="0001.ply: unreadable ASCII vertex data"):
        ReplayScanner(tmp_path).capture()
