"""Loading what several subcommands share (configuration, DBC, model, data), with CLI error codes."""

from __future__ import annotations

from typing import Any

from cmcan import config as cfgmod
from cmcan.cli.errors import EX_CONFIG, EX_DATAERR, EX_NOINPUT, CliError
from cmcan.dbc import DbcError
from cmcan.schema import SchemaError


def load_config(path: str | None, check_dbc: bool = True) -> cfgmod.Config:
    """The configuration (sysexits on any problem), with its DBC loaded and the mapping checked."""
    from cmcan.preflight import load_config as load

    cfg = load(path)
    if check_dbc:
        try:
            cfgmod.check_against_dbc(cfg, cfg.dbc())
        except SchemaError as exc:
            raise CliError(str(exc), EX_CONFIG) from None
        except DbcError as exc:
            raise CliError(f"{exc} (dbc: in {cfg.source})", EX_CONFIG) from None
    return cfg


def load_points(path: str, cfg: cfgmod.Config) -> Any:
    from cmcan.model.features import DataError, load_operating_points

    try:
        return load_operating_points(path, cfg.gate_limits, cfg.dbc(), cfg.signals, cfg.raw["evaluation"]["rate_hz"])
    except DataError as exc:
        code = EX_NOINPUT if "file not found" in str(exc) else EX_DATAERR
        raise CliError(str(exc), code) from None


def load_model_for(cfg: cfgmod.Config, path: str | None = None) -> Any:
    from cmcan.model import ModelError, load_model

    try:
        return load_model(path or cfg.model_path, motor_disp_cc=cfg.motor_disp_cc)
    except ModelError as exc:
        code = EX_NOINPUT if "not found" in str(exc) else EX_CONFIG
        raise CliError(str(exc), code) from None
