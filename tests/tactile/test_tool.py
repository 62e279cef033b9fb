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
