"""``celld calib solve`` and ``celld calib detect``: offline solving of saved sessions, one-cloud detection."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from celld.calib.dataset import SessionWriter, write_cloud
from celld.calib.flange import preset
from celld.cli import main
from celld.se3 import apply, error, invert, transform_from

T_BASE_CAM = np.array([[0.0, -1.0, 0.0, 0.6], [-1.0, 0.0, 0.0, -0.0125], [0.0, 0.0, -1.0, 1.0], [0.0, 0.0, 0.0, 1.0]])
# Workspace of the calibration poses (the camera is 1 m above the base).
BOX_CENTRE = np.array([0.6, 0.0, 0.35])
BOX_SIZE = np.array([0.3, 0.3, 0.2])


def run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, dict]:
    code = main(list(argv))
    out = capsys.readouterr().out.strip().splitlines()
    return code, json.loads(out[-1])


def flange_poses(rng: np.random.Generator, n: int) -> np.ndarray:
    P = BOX_CENTRE + rng.uniform(-0.5, 0.5, (n, 3)) * BOX_SIZE
    R = Rotation.from_euler("xyz", rng.uniform(-0.3, 0.3, (n, 3))).as_matrix()
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3], T[:, :3, 3] = R, P
    return T


def reference_session(root: Path, rng: np.random.Generator, n: int, sigma: float, outliers: dict[int, list[float]]) -> None:
    """A session in the reference toolbox's format (centres recorded, mm / m / wxyz)."""
    root.mkdir()
    doc = {}
    for i, T in enumerate(flange_poses(rng, n)):
        p_cam = apply(invert(T_BASE_CAM), T[:3, 3][None])[0] + rng.normal(0.0, sigma, 3) + outliers.get(i, 0.0)
        q = Rotation.from_matrix(T[:3, :3]).as_quat()  # x, y, z, w
        doc[str(i)] = {"p_cam": (p_cam * 1e3).tolist(), "p_robot": T[:3, 3].tolist(), "robot_pose": T[:3, 3].tolist() + [q[3], q[0], q[1], q[2]]}
    (root / "calib_data.json").write_text(json.dumps(doc))


def test_solve_reference_session_rejects_the_false_detection(tmp_path: Path, rng: np.random.Generator, capsys) -> None:
    reference_session(tmp_path / "ref", rng, 12, 0.0002, {3: [0.03, -0.01, 0.0]})
    code, out = run(capsys, "calib", "solve", str(tmp_path / "ref"), "--json")
    assert code == 0
    assert out["rejected"] == ["3"]
    assert out["pairs"] == [str(i) for i in range(12) if i != 3]
    assert len(out["residuals_mm"]) == 11 and max(out["residuals_mm"]) < 1.5
    assert out["format"] == "reference" and out["method"] == "robust"
    dt, dr = error(np.array(out["T_base_cam"]), T_BASE_CAM)
    assert dt < 0.001 and np.degrees(dr) < 0.1
    assert out["uncertainty"]["translation_error_mm"] > 0.0
    assert out["e_icp"] is None and "algorithm1" not in out  # no verification cloud in this format


def test_solve_svd_keeps_every_pair_and_pays_for_it(tmp_path: Path, rng: np.random.Generator, capsys) -> None:
    reference_session(tmp_path / "ref", rng, 12, 0.0002, {3: [0.03, -0.01, 0.0]})
    code, out = run(capsys, "calib", "solve", str(tmp_path / "ref"), "--json", "--method", "svd")
    assert code == 0 and out["rejected"] == [] and len(out["pairs"]) == 12
    assert error(np.array(out["T_base_cam"]), T_BASE_CAM)[0] > 0.002


def test_solve_errors_are_json_with_a_reason(tmp_path: Path, rng: np.random.Generator, capsys) -> None:
    code, out = run(capsys, "calib", "solve", str(tmp_path / "nothing"), "--json")
    assert code == 2 and "not a directory" in out["error"]
    reference_session(tmp_path / "ref", rng, 6, 0.0, {})
    code, out = run(capsys, "calib", "solve", str(tmp_path / "ref"), "--json", "--method", "algorithm1")
    assert code == 2 and "verification cloud" in out["error"]
    reference_session(tmp_path / "few", rng, 3, 0.0, {})
    code, out = run(capsys, "calib", "solve", str(tmp_path / "few"), "--json")
    assert code == 2 and "only 3 of 3 pairs" in out["error"]


@pytest.fixture(scope="module")
def sim_sessions(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A small session from the ray-cast PhoXi M (0.4 of its resolution), 8 poses and a verification capture,
    saved twice: compact (the default) and as float32 PLY."""
    from celld.sim.scanner import SimScanner
    from celld.sim.scene import robot_scene

    root = tmp_path_factory.mktemp("sim")
    flange = preset("ur10e")
    scanner = SimScanner("phoxi-m", T_BASE_CAM, seed=1, resolution_scale=0.4)
    writers = [SessionWriter(root / kind, flange="ur10e", scanner="phoxi-m", compact=kind == "compact") for kind in ("compact", "float")]
    T_v = transform_from(np.eye(3), BOX_CENTRE)
    P_v = scanner.capture(robot_scene(T_v, flange)).points
    for w in writers:
        w.set_verification(T_v, P_v)
    for T in flange_poses(np.random.default_rng(1), 8):
        P = scanner.capture(robot_scene(T, flange)).points
        for w in writers:
            w.add_pair(T, P)
    return {"compact": root / "compact", "float": root / "float"}


@pytest.fixture(scope="module")
def sim_session(sim_sessions: dict[str, Path]) -> Path:
    return sim_sessions["compact"]


@pytest.mark.slow
@pytest.mark.parametrize("redetect", [False, True])
def test_a_compact_session_solves_exactly_as_the_float_one(sim_sessions: dict[str, Path], redetect: bool, capsys) -> None:
    assert (sim_sessions["compact"] / "p000.cloud.json").is_file() and (sim_sessions["float"] / "p000.ply").is_file()
    extra = ["--redetect"] if redetect else []
    code_c, compact = run(capsys, "calib", "solve", str(sim_sessions["compact"]), "--json", *extra)
    code_f, full = run(capsys, "calib", "solve", str(sim_sessions["float"]), "--json", *extra)
    assert code_c == code_f == 0
    # The detector reads the same float32 values in both: the same centres, the same solve, to the bit.
    for key in ("T_base_cam", "pairs", "rejected", "residuals_mm", "uncertainty"):
        assert compact[key] == full[key], key
    assert compact["algorithm1"]["pool"] == full["algorithm1"]["pool"]
    # e_icp runs Open3D's ICP, whose threaded sums differ in the last bits from run to run.
    assert compact["algorithm1"]["cost_mm"] == pytest.approx(full["algorithm1"]["cost_mm"], rel=1e-9)
    assert compact["e_icp"]["translation_mm"] == pytest.approx(full["e_icp"]["translation_mm"], rel=1e-9, abs=1e-12)


@pytest.mark.slow
def test_solve_a_saved_simulated_session_end_to_end(sim_session: Path, capsys) -> None:
    code, out = run(capsys, "calib", "solve", str(sim_session), "--json")
    assert code == 0
    assert out["format"] == "celld" and out["flange"] == "ur10e"
    assert len(out["pairs"]) + len(out["rejected"]) == 8 and len(out["pairs"]) >= 6
    dt, dr = error(np.array(out["T_base_cam"]), T_BASE_CAM)
    assert dt < 0.5e-3 and np.degrees(dr) < 0.1
    assert out["e_icp"]["ok"] is True
    assert out["algorithm1"]["steps"][0]["k"] == 0 and len(out["algorithm1"]["pool"]) == 4
    code, out = run(capsys, "calib", "solve", str(sim_session), "--json", "--method", "algorithm1")
    assert code == 0 and len(out["pairs"]) == 4
    assert len(out["rejected"]) == 4 + sum("detection" in r["reason"] for r in out["rejected_detail"])


@pytest.mark.slow
def test_detect_one_cloud_in_millimetres(sim_session: Path, tmp_path: Path, capsys) -> None:
    from celld.calib.dataset import load_session

    session = load_session(sim_session)
    rec = session.pairs[0]
    write_cloud(tmp_path / "mm.ply", session.cloud(rec) * 1e3)
    code, out = run(capsys, "calib", "detect", str(tmp_path / "mm.ply"), "--flange", "ur10e", "--units", "mm", "--json")
    assert code == 0
    true_mm = apply(invert(T_BASE_CAM), rec.p_base[None])[0] * 1e3
    assert np.linalg.norm(np.array(out["center"]) - true_mm) < 0.5  # in the cloud's units, mm
    assert out["radius"] == pytest.approx(31.0, abs=1.0) and out["inliers"] > 30
    assert np.linalg.norm(out["normal"]) == pytest.approx(1.0)
    code, out = run(capsys, "calib", "detect", str(tmp_path / "mm.ply"), "--flange", "ur10e", "--units", "m", "--json")
    assert code == 2 and "millimetres" in out["error"]


def test_detect_reports_errors_as_json(tmp_path: Path, rng: np.random.Generator, capsys) -> None:
    code, out = run(capsys, "calib", "detect", str(tmp_path / "missing.ply"), "--flange", "ur10e", "--units", "m", "--json")
    assert code == 2 and "not found" in out["error"]
    plane = np.column_stack([rng.uniform(-0.2, 0.2, (5000, 2)), np.full(5000, 0.7)])
    write_cloud(tmp_path / "plane.ply", plane)
    code, out = run(capsys, "calib", "detect", str(tmp_path / "plane.ply"), "--flange", "ur10e", "--units", "m", "--json")
    assert code == 2 and "flange detection failed" in out["error"]
    code, out = run(capsys, "calib", "detect", str(tmp_path / "plane.ply"), "--flange", "nope", "--units", "m", "--json")
    assert code == 2 and "unknown flange" in out["error"]


def test_solve_takes_the_method_from_the_cell_config(tmp_path: Path, rng: np.random.Generator, capsys) -> None:
    reference_session(tmp_path / "ref", rng, 8, 0.0002, {})
    (tmp_path / "cell.toml").write_text('[calibration]\nmethod = "svd"\nicp_max_distance_mm = 2.0\n')
    code, out = run(capsys, "calib", "solve", str(tmp_path / "ref"), "--json", "--config", str(tmp_path / "cell.toml"))
    assert code == 0 and out["method"] == "svd"
    code, out = run(capsys, "calib", "solve", str(tmp_path / "ref"), "--json", "--config", str(tmp_path / "cell.toml"), "--method", "robust")
    assert code == 0 and out["method"] == "robust"
    (tmp_path / "bad.toml").write_text('[calibration]\nmethod = "magic"\n')
    code, out = run(capsys, "calib", "solve", str(tmp_path / "ref"), "--json", "--config", str(tmp_path / "bad.toml"))
    assert code == 2 and "calibration.method" in out["error"]
