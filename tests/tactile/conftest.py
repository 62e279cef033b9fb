"""Fixtures for the tactile tests: the default tool, a renderer and a detector."""

from __future__ import annotations

import numpy as np
import pytest

from celld.config import TactileConfig, ToolConfig
from celld.se3 import invert
from celld.sim.srm import Imaging, TagRenderer, tag_pose_tool
from celld.tactile.aruco import TagDetector
from celld.tactile.tool import ToolGeometry


class Scene:
    """Renders the finger's tag for a tip shift in the tool frame and detects it."""

    def __init__(self, cfg: TactileConfig, seed: int = 1, tag_id: int | None = None) -> None:
        self.cfg = cfg
        self.tool_cfg = ToolConfig()
        self.tool = ToolGeometry.from_config(self.tool_cfg)
        self.renderer = TagRenderer(
            cfg.tag_dictionary,
            cfg.tag_id if tag_id is None else tag_id,
            cfg.tag_size,
            cfg.intrinsics_px,
            (cfg.width_px, cfg.height_px),
            seed=seed,
        )
        self.detector = TagDetector.from_config(cfg)
        self.T_cam_tool = invert(self.tool.T_tool_cam)

    def T_cam_tag(self, tip_shift_tool: np.ndarray) -> np.ndarray:
        return self.T_cam_tool @ tag_pose_tool(np.asarray(tip_shift_tool, dtype=np.float64), 0.04)

    def image(self, tip_shift_tool, imaging: Imaging = Imaging()) -> np.ndarray:
        return self.renderer.render(self.T_cam_tag(tip_shift_tool), imaging)

    def detect(self, tip_shift_tool, imaging: Imaging = Imaging()):
        return self.detector.detect(self.image(tip_shift_tool, imaging))


@pytest.fixture
def cfg() -> TactileConfig:
    return TactileConfig()


@pytest.fixture
def scene(cfg: TactileConfig) -> Scene:
    return Scene(cfg)
