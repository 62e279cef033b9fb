"""The dashboard server's commands (port 29999): one line in, one line out (pure).

Replies are those of a PolyScope 5.11 dashboard server, as far as ur-rtde's
``DashboardClient`` and ``RTDEControlInterface`` parse them. ``.urp`` programs
are not simulated: ``load`` accepts any ``.urp`` name and ``play`` runs it as a
program that does nothing until ``stop``.
"""

from __future__ import annotations

from typing import NamedTuple

from celld.sim.robot import controller as c

WELCOME = "Connected: Universal Robots Dashboard Server"
# Build date shown with the version.
_BUILD_DATE = "Jul 14 2023"


class Reply(NamedTuple):
    """The reply line (without newline) and whether the server closes the connection after it."""

    text: str
    close: bool = False


def handle(ctrl: c.Controller, line: str) -> Reply:
    """Execute one dashboard command on ``ctrl`` and return its reply."""
    raw = line.strip()
    cmd = raw.lower()
    arg = raw.split(" ", 1)[1].strip() if " " in raw else ""
    version = ".".join(map(str, ctrl.options.version))
    if cmd == "polyscopeversion":
        return Reply(f"URSoftware {version} ({_BUILD_DATE})")
    if cmd == "version":
        return Reply(f"Version: {version}")
    if cmd == "get serial number":
        return Reply(ctrl.options.serial_number)
    if cmd == "get robot model":
        return Reply("UR10")
    if cmd == "is in remote control":
        return Reply("true" if ctrl.options.remote_control else "false")
    if cmd == "robotmode":
        return Reply(f"Robotmode: {c.ROBOT_MODE_NAMES.get(ctrl.robot_mode, 'NO_CONTROLLER')}")
    if cmd == "safetymode":
        return Reply(f"Safetymode: {c.SAFETY_NAMES.get(ctrl.safety_mode, 'FAULT')}")
    if cmd == "safetystatus":
        return Reply(f"Safetystatus: {c.SAFETY_NAMES.get(ctrl.safety_mode, 'FAULT')}")
    if cmd == "power on":
        ctrl.power_on()
        return Reply("Powering on")
    if cmd == "power off":
        ctrl.power_off()
        return Reply("Powering off")
    if cmd == "brake release":
        ctrl.brake_release()
        return Reply("Brake releasing")
    if cmd == "unlock protective stop":
        refusal = ctrl.unlock_protective_stop()
        return Reply(refusal or "Protective stop releasing")
    if cmd in ("close safety popup", "close popup"):
        return Reply(f"closing {'safety ' if 'safety' in cmd else ''}popup")
    if cmd.startswith("popup"):
        return Reply("showing popup")
    if cmd == "restart safety":
        if ctrl.estop_pressed:
            return Reply("Restarting safety")
        ctrl.safety_mode = c.SAFETY_NORMAL
        ctrl.power_off()
        return Reply("Restarting safety")
    if cmd == "running":
        return Reply(f"Program running: {'true' if ctrl.runtime_state == c.RUNTIME_PLAYING else 'false'}")
    if cmd == "programstate":
        name = ctrl.program_name if ctrl.program is not None else (ctrl.loaded_program or "<unnamed>")
        return Reply(f"{c.RUNTIME_NAMES.get(ctrl.runtime_state, 'STOPPED')} {name}")
    if cmd == "stop":
        # ur-rtde sends "stop" after its own script has ended and needs "Stopped" then too.
        if ctrl.runtime_state in (c.RUNTIME_PLAYING, c.RUNTIME_PAUSED):
            ctrl.stop_program("stopped from the dashboard")
        return Reply("Stopped")
    if cmd == "pause":
        return Reply("Pausing program" if ctrl.pause_program() else "Failed to execute: pause")
    if cmd == "play":
        if ctrl.resume_program():
            return Reply("Starting program")
        if ctrl.loaded_program and ctrl.runtime_state == c.RUNTIME_STOPPED and ctrl.can_run:
            ctrl.start_idle_program(ctrl.loaded_program)
            return Reply("Starting program")
        return Reply("Failed to execute: play")
    if cmd.startswith("load installation"):
        return Reply(f"Loading installation: {arg.split(' ', 1)[-1]}")
    if cmd.startswith("load "):
        if not arg.endswith(".urp"):
            return Reply(f"File not found: {arg}")
        ctrl.loaded_program = arg
        return Reply(f"Loading program: {arg}")
    if cmd == "get loaded program":
        return Reply(f"Loaded program: {ctrl.loaded_program}" if ctrl.loaded_program else "No program loaded")
    if cmd == "isprogramsaved":
        return Reply(f"True {ctrl.loaded_program or '<unnamed>'}")  # capital T, as PolyScope answers
    if cmd.startswith("addtolog"):
        return Reply("Added log message" if arg else "No log message to add")
    if cmd.startswith("setuserrole"):
        return Reply(f"Setting user role: {arg}")
    if cmd == "get operational mode":
        return Reply("NONE")
    if cmd.startswith("set operational mode"):
        return Reply(f"Operational mode '{arg.split(' ')[-1]}' is set")
    if cmd == "clear operational mode":
        return Reply("No longer controlling the operational mode. Current operational mode: 'NONE'.")
    if cmd == "shutdown":
        ctrl.power_off()
        return Reply("Shutting down")
    if cmd == "quit":
        return Reply("Disconnected", close=True)
    return Reply(f"could not understand: '{raw}'")
