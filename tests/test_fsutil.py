"""Atomic writes: the final name holds the old content or the whole new one."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from celld import fsutil


def test_bytes_json_and_arrays_round_trip(tmp_path: Path, rng: np.random.Generator) -> None:
    assert fsutil.write_bytes(tmp_path / "a.bin", b"\x00\x01").read_bytes() == b"\x00\x01"
    fsutil.write_json(tmp_path / "a.json", {"T_base_cam": np.eye(4).tolist(), "cost_mm": 0.21})
    assert json.loads((tmp_path / "a.json").read_text())["cost_mm"] == 0.21
    P_cam = rng.normal(size=(100, 3))
    np.testing.assert_array_equal(np.load(fsutil.write_npy(tmp_path / "p.npy", P_cam)), P_cam)
    with np.load(fsutil.write_npz(tmp_path / "d.npz", P_cam=P_cam, q=np.zeros(6))) as z:
        np.testing.assert_array_equal(z["P_cam"], P_cam)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.bin", "a.json", "d.npz", "p.npy"]


def test_replacing_keeps_the_old_file_until_the_new_one_is_whole(tmp_path: Path) -> None:
    target = tmp_path / "result.json"
    fsutil.write_text(target, "old")
    with pytest.raises(RuntimeError):
        with fsutil.atomic_open(target) as f:
            f.write(b"half of the new")
            assert target.read_text() == "old"
            raise RuntimeError("the writer fails")
    assert target.read_text() == "old"
    assert list(tmp_path.iterdir()) == [target]  # the temporary file is gone


def test_nan_is_refused_and_nothing_is_written(tmp_path: Path) -> None:
    with pytest.raises(ValueError):
        fsutil.write_json(tmp_path / "x.json", {"e": float("nan")})
    assert list(tmp_path.iterdir()) == []


def test_permissions_and_stale_temporaries(tmp_path: Path) -> None:
    old = os.umask(0o022)
    try:
        path = fsutil.write_bytes(tmp_path / "secret", b"x", mode=0o600)
    finally:
        os.umask(old)
    assert path.stat().st_mode & 0o777 == 0o600
    (tmp_path / "sub").mkdir()
    stale = [tmp_path / f".a.json.1234{fsutil.TEMP_SUFFIX}", tmp_path / "sub" / f".b.npy.99{fsutil.TEMP_SUFFIX}"]
    for p in stale:
        p.write_bytes(b"partial")
    keep = tmp_path / "notes.tmp"
    keep.write_text("not ours")
    assert sorted(fsutil.remove_stale_temporaries(tmp_path)) == sorted(stale)
    assert keep.exists() and not any(p.exists() for p in stale)
