"""The motion process's spec from the config: the process output is wired from [robot] arc_output."""

from __future__ import annotations

import pytest

from celld.config import parse
from celld.errors import ConfigError
from celld.motion.channels import ChannelNames
from celld.motion.handle import spec_from_config

NAMES = ChannelNames.unique(64)


def test_the_arc_output_of_the_robot_section_is_the_loop_process_output() -> None:
    assert spec_from_config(parse({}), NAMES).loop.process_output == -1
    assert spec_from_config(parse({"robot": {"arc_output": 5}}), NAMES).loop.process_output == 5


@pytest.mark.parametrize("bad", [8, -2, 1.0, True, "0"])
def test_an_arc_output_that_is_no_standard_output_is_refused(bad: object) -> None:
    with pytest.raises(ConfigError, match="arc_output"):
        parse({"robot": {"arc_output": bad}})
