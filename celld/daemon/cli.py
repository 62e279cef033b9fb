"""``celld run``: the daemon, as systemd starts it; ``celld bus schema``: the bundle of the bus it serves;
``celld journal check|set-aside``: its job journal, checked, and set aside when damaged; ``celld backup``:
its state in one file (:mod:`celld.daemon.statedir`).

``bus schema`` is the daemon's command, not the bus's: the bundle holds each
job kind's result schema, which lives with the runners above the bus
(:data:`celld.daemon.results.BUNDLE`).
"""

from __future__ import annotations

import argparse

from celld.cliparse import CONFIG_HELP, default_config

TAKE_OVER_HELP = "take the robot even when another program runs on it (by default celld waits until it stops, and says so in status)"


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("run", help="run the cell daemon (robot link, jobs over zenoh, recordings)")
    p.add_argument("--config", default=default_config(), help=CONFIG_HELP)
    p.add_argument("--take-over", action="store_true", help=TAKE_OVER_HELP)
    p.set_defaults(func=_run)

    b = sub.add_parser("bus", help="bus tools")
    bsub = b.add_subparsers(dest="bus_command", metavar="ACTION", required=True)
    e = bsub.add_parser("schema", help="export the JSON Schema of every bus message and job result, and the AsyncAPI document")
    e.add_argument("--out", required=True, help="directory to write <name>.schema.json files and asyncapi.json into")
    e.set_defaults(func=_schema)

    k = sub.add_parser("backup", help="export the cell's state (calibrations, tool, finger, results, job journal) to one .tar.gz")
    k.add_argument("--config", default=default_config(), help=CONFIG_HELP)
    k.add_argument("--out", help="the file to write (default: celld-backup-<cell>-<UTC time>.tar.gz in this directory)")
    k.add_argument("--with-datasets", action="store_true", help="the saved calibration sessions too (large: their clouds)")
    k.add_argument("--json", action="store_true", help="print what was written as JSON")
    k.set_defaults(func=_backup)

    j = sub.add_parser("journal", help="the daemon's job journal: check it, set a damaged one aside (with celld stopped)")
    jsub = j.add_subparsers(dest="journal_command", metavar="ACTION", required=True)
    c = jsub.add_parser("check", help="check the journal's integrity; exit 1 when it is damaged")
    a = jsub.add_parser("set-aside", help="move a damaged journal aside (kept as journal-set-aside-<time>.db) and start an empty one")
    a.add_argument("--force", action="store_true", help="set the journal aside even when it is intact")
    for p in (c, a):
        p.add_argument("--config", default=default_config(), help=CONFIG_HELP)
        p.set_defaults(func=_journal)


def _journal(args: argparse.Namespace) -> int:
    from pathlib import Path

    from celld import config as config_mod
    from celld.errors import JournalError
    from celld.journal import Journal

    path = Path(config_mod.load(args.config).cell.state_dir) / "journal.db"
    if not path.exists():
        raise JournalError(f"{path}: no journal here (cell.state_dir of {args.config})")
    with Journal(path, keep_damaged=True) as journal:  # refused while a daemon holds it
        problems = journal.check()
        for problem in problems:
            print(f"{path}: {problem}")
        if args.journal_command == "check":
            print(f"{path}: {'damaged' if problems else 'intact'}")
            return 1 if problems else 0
        if not problems and not args.force:
            print(f"{path}: intact; nothing set aside (--force sets an intact journal aside too)")
            return 1
        aside = journal.set_aside()
    print(f"{path}: set aside as {aside}; a new, empty journal is in its place")
    return 0


def _backup(args: argparse.Namespace) -> int:
    import json
    from pathlib import Path

    from celld import config as config_mod
    from celld.daemon.statedir import default_backup_path, write_backup

    cfg = config_mod.load(args.config)
    out = Path(args.out) if args.out else default_backup_path(cfg.cell.name)
    done = write_backup(Path(cfg.cell.state_dir), out, datasets=args.with_datasets)
    if args.json:
        print(json.dumps(done.as_dict()))
    else:
        print(f"{done.path}: {done.files} files, {done.bytes / 1e6:.1f} MB" + ("" if done.journal else " (no job journal)"))
    return 0


def _run(args: argparse.Namespace) -> int:
    from celld import config as config_mod
    from celld.daemon.app import serve
    from celld.daemon.devices import real_devices

    cfg = config_mod.load(args.config)  # refused here, before any device is opened
    serve(cfg, real_devices(), take_over=args.take_over)
    return 0


def _schema(args: argparse.Namespace) -> int:
    from celld.bus.asyncapi import export_schemas
    from celld.daemon.results import BUNDLE

    for path in export_schemas(args.out, BUNDLE):
        print(path)
    return 0
