"""Bus subcommands: ``celld submit``, ``status``, ``jobs``, ``result``, ``cancel``, ``accept``, ``robot``.

Every subcommand that talks to a cell reads the bus settings from ``--config``
(default ``$CELLD_CONFIG``, else ``/etc/celld/cell.toml``) and addresses the cell named there, or
``--cell``. Credentials: ``--user`` (or ``$CELLD_BUS_USER``, or ``bus.user``)
and ``--password-file`` (or ``$CELLD_BUS_PASSWORD``, or ``bus.password``).

Exit codes: 0 done; 1 a waited-for job ended other than ``succeeded``; 2 a
refused request, a bad argument or no reply (one line on stderr).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

from celld.cliparse import CONFIG_HELP, add_command, default_config
from celld.errors import BusError, ConfigError, JobError

if TYPE_CHECKING:
    from celld import config
    from celld.bus.client import CellClient

# Width of the progress bar, characters.
_BAR = 30


# -- arguments ----------------------------------------------------------------------


def _connection_options() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(add_help=False)
    g = p.add_argument_group("bus")
    g.add_argument("--config", default=default_config(), help=CONFIG_HELP + ", with the bus settings")
    g.add_argument("--cell", help="cell name (default: cell.name of the config)")
    g.add_argument("--user", help="bus user (default $CELLD_BUS_USER, then bus.user)")
    g.add_argument("--password-file", help="file whose first line is the password (default $CELLD_BUS_PASSWORD, then bus.password)")
    g.add_argument("--timeout", type=float, help="reply timeout, s (default bus.query_timeout)")
    g.add_argument("--json", action="store_true", help="print replies as JSON")
    return p


def _floats(n: int, name: str) -> dict[str, Any]:
    return {"nargs": n, "type": float, "metavar": name}


def add_parser(sub: argparse._SubParsersAction) -> None:
    # The choices of submit, jobs and robot come from the schema (numpy, the config): defined when used.
    common = _connection_options()

    add_command(sub, "submit", _submit_arguments, help="submit a job to a cell")

    s = sub.add_parser("status", parents=[common], help="state of a cell, of one job, or of every cell")
    which = s.add_mutually_exclusive_group()
    which.add_argument("--all", action="store_true", help="every cell found on the bus (liveliness)")
    which.add_argument("--job", help="one job's record")
    which.add_argument("--calibration", action="store_true", help="the current calibration")
    s.set_defaults(func=_status)

    add_command(sub, "jobs", _jobs_arguments, parents=[common], help="jobs in a cell's journal, newest first")

    x = sub.add_parser("cancel", parents=[common], help="cancel a queued or running job (the robot stops first)")
    x.add_argument("job")
    x.add_argument("--reason", default="", help="why (kept in the job's record)")
    x.set_defaults(func=_cancel)

    r = sub.add_parser("result", parents=[common], help="a finished job's result, over the bus")
    r.add_argument("job")
    r.add_argument("--out", help="write the result document to this file instead of printing it")
    r.set_defaults(func=_result)

    a = sub.add_parser("accept", parents=[common], help="make a calibrate (tool-calibrate) job's result the current (tool) calibration")
    a.add_argument("job")
    a.add_argument("--force", action="store_true", help="accept even though the calibration failed its quality gate")
    a.set_defaults(func=_accept)

    add_command(
        sub, "robot", _robot_arguments, parents=[common], help="clear a robot fault through its dashboard (refused while a job runs)"
    )


def _submit_arguments(p: argparse.ArgumentParser) -> None:
    from celld.bus import messages

    kinds = p.add_subparsers(dest="kind", metavar="KIND", required=True)
    job_common = argparse.ArgumentParser(add_help=False, parents=[_connection_options()])
    job_common.add_argument("--ref", default="", help="your reference for the job (echoed in status)")
    job_common.add_argument(
        "--request-id", help="your id of this submit: submitting again with the same id returns the same job (idempotent)"
    )
    job_common.add_argument("--wait", action="store_true", help="show progress and wait until the job ends")
    job_common.add_argument("--wait-timeout", type=float, help="give up waiting after this many seconds")

    c = kinds.add_parser("calibrate", parents=[job_common], help="eye-on-base calibration from the flange (Algorithm 1)")
    c.add_argument("--n-poses", type=int, help="calibration poses to generate")
    c.add_argument("--e-required-mm", type=float, help="cost at which Algorithm 1 stops, mm")
    c.add_argument("--k-max", type=int, help="most iterations of Algorithm 1")
    c.add_argument("--poses-file", help="JSON file: a list of UR poses [x, y, z, rx, ry, rz] (m, rad)")
    c.add_argument("--verification-pose", **_floats(6, "V"), help="UR pose of the verification capture")
    c.add_argument("--compensate", action="store_true", help="store the estimate compensated by Eq. 21")
    c.add_argument("--seed", type=int, help="seed of the pose generator")
    c.add_argument("--dry-run", action="store_true", help="plan and check the poses against the cell, do not move")
    c.add_argument("--robot2", action="store_true", help="calibrate the cell's second robot too, and its base in robot 1's (Eq. 5-6)")
    c.add_argument(
        "--arm-poses",
        type=int,
        help="then the arm's kinematic calibration from this many wide poses (0: none; default calibration.arm_poses)",
    )

    t = kinds.add_parser("tool-calibrate", parents=[job_common], help="measure the SRM tip in the TCP frame with the scanner")
    t.add_argument("--n-poses", type=int, help="orientations to present the tool at (default 12)")
    t.add_argument("--max-tilt-deg", type=float, help="largest tilt of the finger from facing the scanner, deg (default 20)")
    t.add_argument(
        "--tip-position", **_floats(3, "X"), help="where the tip is presented, base frame, m (default: the verification pose's position)"
    )
    t.add_argument("--seed", type=int, help="seed of the orientation generator")
    t.add_argument("--dry-run", action="store_true", help="plan and check the poses against the cell, do not move")

    w = kinds.add_parser("weld", parents=[job_common], help="scan, find the seam, touch and track it")
    w.add_argument("--workpiece", help="workpiece model known to the cell (default: the config's weld.workpiece)")
    w.add_argument("--delta-d-mm", type=float, help="desired normal deformation, mm")
    w.add_argument("--k-p", type=float, help="normal gain of Eq. 16, 1/s")
    w.add_argument("--v-const-mm-s", type=float, help="tangential speed, mm/s")
    w.add_argument("--torch-offset-mm", type=float, help="|d| of Eq. 14, mm")
    w.add_argument("--no-arc", action="store_true", help="track without the arc")
    w.add_argument("--procedure", help="the weld procedure (procedures/<name>.toml beside the cell's config)")
    w.add_argument("--dry-run", action="store_true", help="scan (the arm at the scan pose), plan and check the weld, do not move")

    m = kinds.add_parser("move", parents=[job_common], help="jerk-limited move to joint positions or a TCP pose")
    target = m.add_mutually_exclusive_group(required=True)
    target.add_argument("--joints", **_floats(6, "Q"), help="joint positions, rad")
    target.add_argument("--pose", **_floats(6, "P"), help="TCP pose [x, y, z, rx, ry, rz], m and rad, base frame")
    m.add_argument("--speed-scale", type=float, help="fraction of the configured speed limits (0, 1]")
    m.add_argument("--robot", type=int, choices=(1, 2), help="the robot that moves (2: the cell's second robot, its own base frame)")

    h = kinds.add_parser("health", parents=[job_common], help="health check of the devices")
    h.add_argument("--check", choices=messages.HEALTH_CHECKS, default="all")

    kinds.add_parser("verify", parents=[job_common], help="verify the current calibration against the cell now")

    f = kinds.add_parser("file", parents=[job_common], help="submit a JSON job message from a file ('-': stdin)")
    f.add_argument("path")
    p.set_defaults(func=_submit)


def _jobs_arguments(j: argparse.ArgumentParser) -> None:
    from celld.bus import messages

    j.add_argument("--limit", type=int, default=20)
    j.add_argument("--state", choices=messages.JOB_STATES)
    j.add_argument("--kind", choices=messages.JOB_KINDS)
    j.set_defaults(func=_jobs)


def _robot_arguments(rb: argparse.ArgumentParser) -> None:
    from celld.bus import messages

    rb.add_argument(
        "action",
        choices=messages.ROBOT_ACTIONS,
        help="unlock a protective stop, power the arm on, release its brakes, close the safety pop-up",
    )
    rb.set_defaults(func=_robot)


# -- helpers ------------------------------------------------------------------------


def _bus(args: argparse.Namespace) -> tuple[config.Config, config.BusConfig, str | None, str | None]:
    from celld import config

    cfg = config.load(args.config)
    user = args.user or os.environ.get("CELLD_BUS_USER") or None
    password = os.environ.get("CELLD_BUS_PASSWORD") or None
    if args.password_file:
        try:
            password = Path(args.password_file).read_text(encoding="utf-8").splitlines()[0]
        except (OSError, IndexError, UnicodeDecodeError) as exc:
            raise ConfigError(args.password_file, "", f"cannot read a password from it: {exc}") from exc
    return cfg, cfg.bus, user, password


def _client(args: argparse.Namespace) -> CellClient:
    from celld.bus.client import CellClient

    cfg, bus, user, password = _bus(args)
    return CellClient(bus, args.cell or cfg.cell.name, user=user, password=password, timeout=args.timeout)


def _print_json(value: Any) -> None:
    print(json.dumps(value, indent=2))


def _job_message(args: argparse.Namespace) -> dict[str, Any]:
    from celld.bus import wire
    from celld.bus.checker import describe

    kind = args.kind
    if kind == "file":
        text = sys.stdin.read() if args.path == "-" else Path(args.path).read_text(encoding="utf-8")
        message = wire.load_json(text.encode("utf-8"))
        if not isinstance(message, dict):
            raise JobError("$", f"{args.path}: expected a JSON object (a job message), got {describe(message)}")
        if args.ref:
            message["ref"] = args.ref
        if args.request_id:
            message["request_id"] = args.request_id
        return message
    m: dict[str, Any] = {"kind": kind}
    if kind == "calibrate":
        _put(m, "n_poses", args.n_poses)
        _put(m, "e_required_mm", args.e_required_mm)
        _put(m, "k_max", args.k_max)
        _put(m, "seed", args.seed)
        if args.poses_file:
            m["poses"] = wire.load_json(Path(args.poses_file).read_bytes())
        if args.verification_pose:
            m["verification_pose"] = args.verification_pose
        if args.compensate:
            m["compensate"] = True
        if args.dry_run:
            m["dry_run"] = True
        if args.robot2:
            m["robot2"] = True
        if args.arm_poses is not None:
            m["arm_poses"] = args.arm_poses
    elif kind == "tool-calibrate":
        _put(m, "n_poses", args.n_poses)
        _put(m, "max_tilt_deg", args.max_tilt_deg)
        _put(m, "tip_position", args.tip_position)
        _put(m, "seed", args.seed)
        if args.dry_run:
            m["dry_run"] = True
    elif kind == "weld":
        _put(m, "workpiece", args.workpiece)
        _put(m, "delta_d_mm", args.delta_d_mm)
        _put(m, "k_p", args.k_p)
        _put(m, "v_const_mm_s", args.v_const_mm_s)
        _put(m, "torch_offset_mm", args.torch_offset_mm)
        _put(m, "procedure", args.procedure)
        if args.no_arc:
            m["arc"] = False
        if args.dry_run:
            m["dry_run"] = True
    elif kind == "move":
        m["target"] = {"space": "joint", "q": args.joints} if args.joints else {"space": "cartesian", "pose": args.pose}
        _put(m, "speed_scale", args.speed_scale)
        _put(m, "robot", args.robot)
    elif kind == "health":
        m["check"] = args.check
    if args.ref:
        m["ref"] = args.ref
    if args.request_id:
        m["request_id"] = args.request_id
    return m


def _put(m: dict[str, Any], key: str, value: Any) -> None:
    if value is not None:
        m[key] = value


class ProgressBar:
    """Progress events of one job drawn on a terminal, or as lines when not a terminal."""

    def __init__(self, stream: TextIO | None = None) -> None:
        # The stderr of now, not of import time (it may have been replaced since).
        self.stream = stream if stream is not None else sys.stderr
        self.tty = self.stream.isatty()
        self._last: tuple[str, int] | None = None
        self._drawn = False

    def update(self, event: dict[str, Any]) -> None:
        fraction = event.get("fraction")
        stage = str(event.get("stage", ""))
        text = str(event.get("message", ""))
        pct = int(round(100 * fraction)) if isinstance(fraction, (int, float)) else -1
        if self.tty:
            filled = max(0, pct) * _BAR // 100
            bar = "#" * filled + "-" * (_BAR - filled)
            shown = f"{pct:3d}%" if pct >= 0 else "  ?%"
            self.stream.write(f"\r[{bar}] {shown} {event.get('state', '')} {stage}: {text}"[:160].ljust(100))
            self._drawn = True
        else:
            key = (stage, pct // 10)
            if key != self._last:
                self._last = key
                shown = f"{pct}%" if pct >= 0 else "?"
                self.stream.write(f"{event.get('job', '')} {event.get('state', '')} {stage} {shown} {text}\n")
        self.stream.flush()

    def close(self) -> None:
        if self.tty and self._drawn:
            self.stream.write("\n")
            self.stream.flush()


# -- subcommands --------------------------------------------------------------------


def _submit(args: argparse.Namespace) -> int:
    message = _job_message(args)
    with _client(args) as cell:
        if not args.wait:
            reply = cell.submit(message)
            if args.json:
                _print_json(reply)
            else:
                print(
                    f"{reply['job']} {reply['state']}"
                    + (f" (position {reply['position']})" if reply["state"] == "queued" else "")
                    + (" (replayed: this request id made it before)" if reply.get("replayed") else "")
                )
            return 0
        bar = ProgressBar()
        try:
            with cell.watch_progress() as events:
                reply = cell.submit(message)
                print(f"{reply['job']} {reply['state']}", file=sys.stderr)
                record = events.wait(reply["job"], bar.update, args.wait_timeout)
        finally:
            bar.close()
        if args.json:
            _print_json(record)
        else:
            _print_record(record)
        return 0 if record["state"] == "succeeded" else 1


def _print_record(r: dict[str, Any]) -> None:
    line = f"{r['id']} {r['kind']} {r['state']}"
    if r.get("reason"):
        line += f": {r['reason']}"
    if r.get("result"):
        line += f" -> {r['result']}"
    if r.get("redacted"):
        line += " (details withheld from this user)"
    print(line)


def _status(args: argparse.Namespace) -> int:
    if args.all:
        return _status_all(args)
    with _client(args) as cell:
        if args.job:
            record = cell.status(args.job)
            if args.json:
                _print_json(record)
            else:
                _print_record(record)
        elif args.calibration:
            _print_json(cell.calibration())
        else:
            reply = cell.status()
            if args.json:
                _print_json(reply)
            else:
                _print_status(reply)
    return 0


def _print_status(s: dict[str, Any]) -> None:
    queued = ", ".join(s.get("queued", [])) or "-"
    storage = s.get("storage") or {}
    free = storage.get("free_mb")
    print(
        f"{s.get('cell', '?')}: {s.get('state', '?')}  running {s.get('running') or '-'}  queued {queued}  "
        f"robot {s.get('robot_link', '?')}  calibration {s.get('calibration') or '-'}"
        + (f"  free {free:.0f} MB" if isinstance(free, (int, float)) else "")
    )
    if s.get("message"):
        print(f"  {s['message']}")
    robot = s.get("robot")
    if isinstance(robot, dict) and not robot.get("ready", True):
        _print_robot(robot)


def _status_all(args: argparse.Namespace) -> int:
    from celld.bus.client import CellClient, discover_cells
    from celld.bus.session import open_client

    _, bus, user, password = _bus(args)
    session = open_client(bus, user, password)
    try:
        cells = discover_cells(bus, session=session)
        out = []
        for name in cells:
            try:
                out.append(CellClient(bus, name, user=user, session=session, timeout=args.timeout).status())
            except BusError as exc:
                out.append({"ok": False, "cell": name, "error": {"field": "", "reason": str(exc)}})
    finally:
        session.close()
    if args.json:
        _print_json(out)
    elif not out:
        print(f"no cell found under {bus.prefix}/")
    else:
        for s in out:
            if s.get("ok"):
                _print_status(s)
            else:
                print(f"{s['cell']}: no status ({s['error']['reason']})")
    return 0


def _jobs(args: argparse.Namespace) -> int:
    with _client(args) as cell:
        jobs = cell.list(args.limit, args.state, args.kind)
    if args.json:
        _print_json(jobs)
    else:
        for r in jobs:
            print(f"{r['id']}  {r['kind']:<9} {r['state']:<11} {r['created']}  {r.get('ref', '')}")
    return 0


def _cancel(args: argparse.Namespace) -> int:
    with _client(args) as cell:
        reply = cell.cancel(args.job, args.reason)
    if args.json:
        _print_json(reply)
    else:
        print(f"{reply['job']} {reply['state']}")
    return 0


def _result(args: argparse.Namespace) -> int:
    from celld.bus import messages

    with _client(args) as cell:
        reply = cell.result(args.job)
    if args.out:
        if reply["result"] is None:
            raise JobError(
                "$.job",
                f"job {args.job} ({reply['state']}) has no result to write"
                + (f": it is over {messages.MAX_RESULT_BYTES} bytes, on the cell PC at {reply.get('path')}" if reply["too_large"] else ""),
            )
        Path(args.out).write_text(json.dumps(reply["result"], indent=2) + "\n", encoding="utf-8")
        print(args.out)
    elif args.json:
        _print_json(reply)
    else:
        print(f"{reply['job']} {reply['kind']} {reply['state']}" + (f": {reply['reason']}" if reply["reason"] else ""))
        if reply["too_large"]:
            print(f"result over {messages.MAX_RESULT_BYTES} bytes: on the cell PC at {reply.get('path')}")
        elif reply["result"] is not None:
            print(json.dumps(reply["result"], indent=2))
        for f in reply["files"]:
            print(f"file on the cell PC: {f['path']} ({f['bytes']} bytes)")
    return 0


def _accept(args: argparse.Namespace) -> int:
    with _client(args) as cell:
        reply = cell.accept(args.job, force=args.force)
    if args.json:
        _print_json(reply)
    else:
        what = "tool calibration" if reply.get("kind") == "tool-calibrate" else "calibration"
        value = reply.get("tool") if reply.get("kind") == "tool-calibrate" else reply.get("calibration")
        forced = " (forced past a failed quality verdict)" if (value or {}).get("forced") else ""
        print(f"{what} of {reply['job']} is current{forced}")
    return 0


def _robot(args: argparse.Namespace) -> int:
    with _client(args) as cell:
        reply = cell.robot(args.action)
    if args.json:
        _print_json(reply)
    else:
        print(f"{args.action}: {reply['reply'] or 'sent'}")
        _print_robot(reply["robot"])
    return 0


def _print_robot(robot: dict[str, Any]) -> None:
    if robot.get("ready"):
        print(f"robot ready (mode {robot.get('mode') or '?'}, safety {robot.get('safety') or '?'})")
    else:
        print(f"robot {robot.get('state')}: {robot.get('reason')}")
        if robot.get("remedy"):
            print(f"  to clear it: {robot['remedy']}")
