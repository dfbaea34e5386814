"""Loading what several subcommands share: configuration (checked against its DBC), model, data."""

from __future__ import annotations

import argparse
import logging
from typing import TYPE_CHECKING, Any, Protocol

from cmcan.errors import CmcanError, Kind

if TYPE_CHECKING:  # the rest is imported where used: every subcommand's parser imports this module
    from cmcan import config as cfgmod

log = logging.getLogger("cmcan")


class Subparsers(Protocol):
    """What a subcommand's module uses of ``add_subparsers()``'s result (argparse's class is private)."""

    def add_parser(self, name: str, **kwargs: Any) -> argparse.ArgumentParser: ...


def load_config(path: str | None, check_dbc: bool = True) -> cfgmod.Config:
    """The configuration, with its DBC loaded and the mapping checked (errors carry their kind)."""
    from cmcan.assemble import check_against_dbc, dbc_for
    from cmcan.daemon.preflight import load_config as read_config

    cfg = read_config(path)
    if check_dbc:
        check_against_dbc(cfg, dbc_for(cfg))
    return cfg


def load_points(
    path: str, cfg: cfgmod.Config, envelope: dict[str, tuple[float, float]] | None = None, keep_truncated: bool = False
) -> Any:
    """Operating points of a run CSV or a CAN log, gated by the configuration's rules; a log cut short
    is refused, or with ``keep_truncated`` read up to its last whole frame (a warning says where)."""
    from cmcan.assemble import dbc_for, fitted_limits, frame_matcher
    from cmcan.model.features import load_operating_points

    db = dbc_for(cfg)
    match = frame_matcher(cfg, db)
    op = load_operating_points(
        path, fitted_limits(cfg, db)[0], db, cfg.signals, cfg.rate_hz, cfg.drive.fixed, envelope, match, keep_truncated
    )
    note = match.merged_note(cfg)
    if note is not None:
        log.warning("%s: %s", path, note)
    return op


def load_model(cfg: cfgmod.Config, path: str | None = None) -> Any:
    from cmcan.assemble import load_model_for

    return load_model_for(cfg, path)


# -- data options shared by train and score ------------------------------------------------------

KEEP_TRUNCATED_HELP = (
    "read a CAN log cut short (a logger stopped mid-write: its last line cut, a compressed file or a BLF "
    "object ending early) up to its last whole frame, with a warning naming the cut; without it such a "
    "log is refused (exit 65)"
)


def add_keep_truncated(p: argparse.ArgumentParser) -> None:
    p.add_argument("--keep-truncated", action="store_true", help=KEEP_TRUNCATED_HELP)


def add_data_options(p: argparse.ArgumentParser) -> None:
    add_keep_truncated(p)
    p.add_argument(
        "--points",
        action="store_true",
        help="DATA is an operating-point table: one row per operating point (e.g. a cycle mean), "
        "columns mapped to roles by the configuration's points: section",
    )
    p.add_argument(
        "--where",
        action="append",
        default=[],
        metavar="COLUMN=VALUE",
        help="keep only points where this holds (also !=, <, <=, >, >=; repeatable, all must hold): a table's "
        "column, or a role's window mean (pump_speed_rpm, temp_c, ...), time_s, operating_h or a ground-truth "
        "column of a time series",
    )
    p.add_argument(
        "--column", action="append", default=[], metavar="ROLE=COLUMN", help="with --points: read ROLE from COLUMN"
    )
    p.add_argument(
        "--constant",
        action="append",
        default=[],
        metavar="ROLE=VALUE",
        help="with --points: ROLE is this constant (a quantity the machine has no sensor for)",
    )


def _pairs(items: list[str], option: str) -> dict[str, str]:
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip() or not value.strip():
            raise CmcanError(f"{option} {item!r}: expected ROLE=VALUE", Kind.USAGE)
        out[key.strip()] = value.strip()
    return out


def conditions(args: argparse.Namespace) -> tuple[Any, ...]:
    from cmcan.io.points import Condition, PointsError

    try:
        return tuple(Condition.parse(w) for w in args.where)
    except PointsError as exc:
        raise CmcanError(str(exc), Kind.USAGE) from None


def load_data(
    args: argparse.Namespace, cfg: cfgmod.Config, envelope: dict[str, tuple[float, float]] | None = None
) -> Any:
    """The operating points of ``args.data`` (a table with --points, else a time series) and the
    mask of those --where keeps (a table's rows are filtered as they are read)."""
    from cmcan.roles import MODEL_INPUTS

    conds = conditions(args)
    if not args.points:
        if args.column or args.constant:
            raise CmcanError("--column and --constant need --points (an operating-point table)", Kind.USAGE)
        op = load_points(args.data, cfg, envelope, args.keep_truncated)
        return op, op.where(conds)
    import numpy as np

    from cmcan.io.points import PointsError, PointSpec, read_points
    from cmcan.model.features import is_log, table_points

    if is_log(args.data):
        raise CmcanError(f"{args.data}: --points reads a CSV table, not a CAN log", Kind.USAGE)
    consts: dict[str, float] = {}
    for role, value in _pairs(args.constant, "--constant").items():
        try:
            consts[role] = float(value)
        except ValueError:
            raise CmcanError(f"--constant {role}={value}: {value!r} is not a number", Kind.USAGE) from None
    roles = (*MODEL_INPUTS, cfg.quantity)
    cols = _pairs(args.column, "--column")
    for role in (*cols, *consts):
        if role not in roles:
            raise CmcanError(f"--column/--constant {role}: not a role of this machine ({', '.join(roles)})", Kind.USAGE)
    spec = cfg.points.merged(PointSpec(cols, consts, conds, "the command line"))
    try:
        # A row with a missing value is judged on its own: the gates refuse it (implausible input);
        # a cell that is neither a number nor a missing value is an error (cmcan.io.points).
        pts = read_points(args.data, spec, roles, missing_as_nan=True)
    except PointsError as exc:  # its kind says whose fault: the file (65, 66) or the points mapping (78)
        raise CmcanError(str(exc), exc.kind) from None
    op = table_points(pts, cfg.gate_limits, envelope)
    return op, np.ones(len(op), dtype=bool)
