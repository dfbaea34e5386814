"""Rebuild the default model shipped with cmcan: ``python -m cmcan.rebuild_default``.

It simulates the healthy training scenario (``training_healthy``), gates it with the shipped
configuration's rules and trains on its first hour (D_trn), testing on the second (D_tst).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from cmcan import config as cfgmod
from cmcan.assemble import dbc_for
from cmcan.model.features import operating_points, series_from_columns
from cmcan.model.runtime import default_model_path
from cmcan.model.train import train_on_points
from cmcan.sim import scenario as scn
from cmcan.sim.run import simulate

SCENARIO = "training_healthy"
T_TRN_H = 1.0


def build(out: Path) -> dict:
    cfg = cfgmod.load()
    s = scn.load(scn.shipped(SCENARIO))
    run = simulate(s, dbc_for(cfg))
    series, truth = series_from_columns(run.columns, SCENARIO)
    op = operating_points(series, cfg.gate_limits, cfg.rate_hz, truth=truth)
    blob, _model, stats = train_on_points(
        op,
        T_TRN_H,
        cfg.motor_disp_cc,
        f"scenario:{SCENARIO}",
        extra_training_info={"scenario_seed": s.seed},
        oil=cfg.oil,
    )
    tmp = out.with_name(out.name + ".tmp")
    tmp.write_bytes(blob)
    tmp.replace(out)
    return stats


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--out", type=Path, default=default_model_path(), help="where to write (default: the shipped model)"
    )
    args = ap.parse_args()
    stats = build(args.out)
    print(
        f"wrote {args.out}: D_tst RMSE {stats['rmse']:.2f} {stats['unit']}, ratio p1..p99 "
        f"{stats['ratio_p1_pct']:.3f}..{stats['ratio_p99_pct']:.3f} %"
    )


if __name__ == "__main__":
    main()
