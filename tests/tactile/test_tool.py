"""The tool geometry and its config: frames as documented in celld.tactile.tool, bad values refused."""

from __future__ import annotations

import numpy as np
import pytest

from celld import config
from celld.errors import ConfigError
from celld.tactile.tool import ToolGeometry


def test_default_tool_frame_matches_the_paper_axes() -> None:
    tool = ToolGeometry.from_config(config.parse({}).tool)
    R = tool.T_tcp_tool[:3, :3]
    # x = t_d along the TCP x, z = finger axis up (TCP z points down the finger), y = z x x.
    np.testing.assert_allclose(R[:, 0], [1, 0, 0])
    np.testing.assert_allclose(R[:, 2], [0, 0, -1])
    np.testing.assert_allclose(R[:, 1], np.cross(R[:, 2], R[:, 0]))
    assert np.linalg.det(R) == pytest.approx(1.0)
    # Eq. 14: the torch trails the undeformed tip by |d| along -t_d.
    np.testing.assert_allclose(tool.torch_tool(), [-0.03, 0.0, 0.0])
    assert tool.side == 1.0
    # The camera looks down the finger at the tip.
    np.testing.assert_allclose(tool.T_tool_cam[:3, 2], [0, 0, -1])
    np.testing.assert_allclose(tool.T_tool_cam[:3, 3], [0, 0, 0.04])


def test_tool_config_converts_units_once_and_refuses_bad_geometry() -> None:
    t = config.parse({"tool": {"tip_tcp_mm": [0, 0, 12.5], "torch_offset_mm": 45, "wall_side": "right", "tool_x_tcp": [0, 2, 0]}}).tool
    assert t.tip_tcp == pytest.approx((0.0, 0.0, 0.0125))
    assert t.torch_offset == pytest.approx(0.045)
    assert t.tool_x_tcp == pytest.approx((0.0, 1.0, 0.0))
    tool = ToolGeometry.from_config(t)
    assert tool.side == -1.0
    np.testing.assert_allclose(tool.T_tcp_tool[:3, 3], [0, 0, 0.0125])
    with pytest.raises(ConfigError, match="perpendicular"):
        config.parse({"tool": {"tool_x_tcp": [1, 0, 0], "tool_z_tcp": [1, 0, 1]}})
    with pytest.raises(ConfigError, match="wall_side"):
        config.parse({"tool": {"wall_side": "up"}})
    with pytest.raises(ConfigError, match="non-zero"):
        config.parse({"tool": {"tool_z_tcp": [0, 0, 0]}})


def test_the_servo_must_ask_for_a_deformation_the_sensor_reads_as_contact() -> None:
    with pytest.raises(ConfigError, match="contact_threshold_mm < delta_d_mm < tactile.overload_mm") as info:
        config.parse({"servo": {"delta_d_mm": 5.0}})
    assert info.value.key == "servo.delta_d_mm"
    with pytest.raises(ConfigError, match="contact_threshold_mm < delta_d_mm"):
        config.parse({"tactile": {"contact_threshold_mm": 2.0}})
    assert config.parse({"servo": {"delta_d_mm": 3.0}, "tactile": {"overload_mm": 3.5}}).servo.delta_d == pytest.approx(0.003)


def test_a_measured_torch_reframes_the_tool_so_eq14_puts_the_torch_on_it() -> None:
    from celld.tactile.tool import with_measured_torch, yaw_in_plane

    cfg = config.parse({"tool": {"tip_tcp_mm": [0.8, -1.1, 200.9]}}).tool
    nominal = ToolGeometry.from_config(cfg)
    torch_nominal = (nominal.T_tcp_tool @ np.append(nominal.torch_tool(), 1.0))[:3]
    torch = torch_nominal + np.array([0.3e-3, -1.2e-3, -0.4e-3])  # bent sideways, trimmed 0.4 mm short (TCP z runs down the finger)
    m = with_measured_torch(cfg, torch)
    tool = ToolGeometry.from_config(m.tool)
    # Eq. 14 in the new frame puts the torch on the measured point, but for its height along the finger.
    on_eq14 = (tool.T_tcp_tool @ np.append(tool.torch_tool(), 1.0))[:3]
    z = tool.T_tcp_tool[:3, 2]
    np.testing.assert_allclose(on_eq14 + m.height * z, torch, atol=1e-12)
    assert m.height == pytest.approx(0.4e-3) and m.tool.torch_offset == pytest.approx(np.hypot(0.03 - 0.3e-3, 1.2e-3))
    # The finger axis, tip and camera stay; the x axis turns about z by -sensor_yaw (about 2.3 deg here).
    np.testing.assert_allclose(z, nominal.T_tcp_tool[:3, 2], atol=1e-12)
    np.testing.assert_allclose(tool.T_tcp_tool[:3, 3], nominal.T_tcp_tool[:3, 3])
    assert m.tool.T_tool_cam == cfg.T_tool_cam
    assert abs(np.degrees(m.sensor_yaw)) == pytest.approx(np.degrees(np.arctan2(1.2, 29.7)), abs=1e-6)
    # A deformation seen in the configured frame, turned by sensor_yaw, is the same vector in the new frame.
    d_tcp = nominal.T_tcp_tool[:3, :3] @ np.array([0.4e-3, 1.5e-3, 0.0])
    in_new = tool.T_tcp_tool[:3, :3].T @ d_tcp
    np.testing.assert_allclose(yaw_in_plane(np.array([0.4e-3, 1.5e-3, 0.0]), m.sensor_yaw), in_new[:2], atol=1e-15)
    # No measurement error: the tool as configured.
    same = with_measured_torch(cfg, torch_nominal)
    assert same.sensor_yaw == pytest.approx(0.0, abs=1e-12) and same.tool.torch_offset == pytest.approx(cfg.torch_offset)


@pytest.mark.parametrize(
    ("offset_mm", "match"),
    [
        ((0.0, 6.0, 0.0), "deg about the finger"),  # 11 deg round
        ((0.0, 0.0, 6.0), "off the tip's height"),
        ((30.0, 0.0, 0.0), "across the finger; torch_offset_mm must be"),  # on the finger's axis
        ((np.nan, 0.0, 0.0), "finite"),
    ],
)
def test_a_measured_torch_that_cannot_be_right_is_refused(offset_mm: tuple[float, float, float], match: str) -> None:
    from celld.errors import InputError
    from celld.tactile.tool import with_measured_torch

    cfg = config.parse({}).tool
    nominal = ToolGeometry.from_config(cfg)
    torch = (nominal.T_tcp_tool @ np.append(nominal.torch_tool(), 1.0))[:3]
    with pytest.raises(InputError, match=match):
        with_measured_torch(cfg, torch + nominal.T_tcp_tool[:3, :3] @ (np.array(offset_mm) * 1e-3))
