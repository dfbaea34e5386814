"""Loading what several subcommands share: configuration (checked against its DBC), model, data."""

from __future__ import annotations

from typing import Any

from cmcan import config as cfgmod
from cmcan.assemble import check_against_dbc, dbc_for, frame_matcher, load_model_for
from cmcan.preflight import load_config as _load_config


def load_config(path: str | None, check_dbc: bool = True) -> cfgmod.Config:
    """The configuration, with its DBC loaded and the mapping checked (errors carry their kind)."""
    cfg = _load_config(path)
    if check_dbc:
        check_against_dbc(cfg, dbc_for(cfg))
    return cfg


def load_points(path: str, cfg: cfgmod.Config) -> Any:
    from cmcan.model.features import load_operating_points

    db = dbc_for(cfg)
    return load_operating_points(path, cfg.gate_limits, db, cfg.signals, cfg.rate_hz, frame_matcher(cfg, db))


def load_model(cfg: cfgmod.Config, path: str | None = None) -> Any:
    return load_model_for(cfg, path)
