"""RTDE codecs of the simulated controller, without sockets."""

from __future__ import annotations

import struct

import pytest

from celld.sim.robot import rtde_protocol as P


def test_package_reader_splits_and_waits_for_partial_packages() -> None:
    stream = P.package(P.REQUEST_PROTOCOL_VERSION, struct.pack(">H", 2)) + P.package(P.GET_URCONTROL_VERSION)
    reader = P.PackageReader()
    reader.feed(stream[:4])
    assert list(reader.packages()) == []
    reader.feed(stream[4:])
    assert list(reader.packages()) == [(P.REQUEST_PROTOCOL_VERSION, b"\x00\x02"), (P.GET_URCONTROL_VERSION, b"")]


@pytest.mark.parametrize("size", [0, 2, P.MAX_PACKAGE_SIZE + 1])
def test_package_reader_refuses_sizes_it_cannot_resynchronise(size: int) -> None:
    reader = P.PackageReader()
    reader.feed(struct.pack(">HB", size, P.DATA_PACKAGE) + b"\x00" * 8)
    with pytest.raises(P.RtdeProtocolError, match="package size"):
        list(reader.packages())


def test_output_setup_parses_frequency_and_tolerates_the_trailing_comma() -> None:
    payload = struct.pack(">d", 500.0) + b"timestamp,actual_q,runtime_state,"
    assert P.parse_setup_outputs(payload) == (500.0, ("timestamp", "actual_q", "runtime_state"))
    with pytest.raises(P.RtdeProtocolError, match="field names"):
        P.parse_setup_outputs(struct.pack(">d", 500.0) + b"timestamp,,actual_q")


def test_types_resolve_by_name_with_not_found() -> None:
    names = ("actual_q", "joint_mode", "actual_digital_output_bits", "output_int_register_47", "no_such_field")
    assert P.resolve(names, P.OUTPUT_FIELDS) == ("VECTOR6D", "VECTOR6INT32", "UINT64", "INT32", P.NOT_FOUND)
    assert P.resolve(("standard_digital_output", "actual_q"), P.INPUT_FIELDS) == ("UINT8", P.NOT_FOUND)


def test_data_round_trip_through_a_recipe() -> None:
    names = ("input_int_register_0", "input_double_register_0", "standard_digital_output_mask", "external_force_torque")
    recipe = P.make_recipe(3, names, P.resolve(names, P.INPUT_FIELDS))
    values = (10, 0.25, 8, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0)
    pkg = P.data_package(recipe, values)
    assert struct.unpack_from(">HB", pkg) == (len(pkg), P.DATA_PACKAGE)
    got_recipe, got = P.parse_data(pkg[3:], {3: recipe})
    assert got_recipe is recipe and got == values
    assert recipe.widths == (1, 1, 1, 6)


def test_data_with_an_unknown_recipe_or_wrong_length_is_refused() -> None:
    recipe = P.make_recipe(1, ("input_int_register_0",), ("INT32",))
    with pytest.raises(P.RtdeProtocolError, match="unknown input recipe id 7"):
        P.parse_data(bytes([7, 0, 0, 0, 0]), {1: recipe})
    with pytest.raises(P.RtdeProtocolError, match="expects 5 bytes, got 3"):
        P.parse_data(bytes([1, 0, 0]), {1: recipe})


def test_replies_have_the_documented_layout() -> None:
    assert P.reply_protocol_version(True) == b"\x00\x04V\x01"
    assert P.reply_controller_version(5, 11, 6, 1) == struct.pack(">HBIIII", 19, ord("v"), 5, 11, 6, 1)
    assert P.reply_setup(P.CONTROL_PACKAGE_SETUP_INPUTS, 2, ("INT32", "IN_USE")) == b"\x00\x10I\x02INT32,IN_USE"
    msg = P.text_message("watchdog", "ctrl", P.LEVEL_ERROR)
    assert msg[3:] == b"\x08watchdog\x04ctrl\x01"
    assert P.parse_text_message(msg[3:]) == ("watchdog", "ctrl", P.LEVEL_ERROR)
