"""The gap diagnosis on operating-point tables and flow machines: nothing depends on a table's row
order, a table's noise comes from neighbours in operating-point space, the monitor's plausibility
gate keeps units gone wrong out, and a flow machine's gates apply to its flow."""

import csv
import json
import re

import numpy as np
import pytest

from cmcan.cli.errors import EX_DATAERR, EX_USAGE
from cmcan.gap import context as ctx_mod
from cmcan.gap import data as gapdata
from cmcan.gap.diagnose import diagnose
from cmcan.gap.effects import Inputs, simulate
from cmcan.gap.report import to_json
from cmcan.io.points import PointSpec
from cmcan.io.runcsv import write_run_csv
from cmcan.monitor.gating import GateLimits
from cmcan.roles import DP, FLOW, MODEL_INPUTS, MOTOR_SPEED, PUMP_DISP, PUMP_SPEED, TEMP
from cmcan.sim.physics import DriveParams
from cmcan.sim.scenario import load_drive
from tests.conftest import ROOT, run_cli

ZEMA = ROOT / "examples" / "zema-rig"
CYCLES = ZEMA / "data" / "cycles.csv"
RIG = load_drive(ZEMA / "drive.yaml")
RIG_SPEC = PointSpec.load(ZEMA / "points.yaml")
P = DriveParams()
NAN = re.compile(r"\bnan\b", re.IGNORECASE)  # JSON writes non-finite numbers as null


def _healthy_rows(every: int = 1) -> tuple[list[str], list[list[str]]]:
    """The rig's healthy cycles (pump_leak=0) as the file holds them, every ``every``-th of them."""
    with open(CYCLES, newline="") as f:
        rows = list(csv.reader(f))
    header, body = rows[0], rows[1:]
    leak = header.index("pump_leak")
    return header, [r for r in body if float(r[leak]) == 0][::every]


def _write(path, header, rows):
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        w.writerows(rows)
    return path


def _report(path) -> dict:
    d = gapdata.load_points(path, RIG_SPEC, FLOW)
    diag, _ = diagnose(d, RIG)
    rep = json.loads(to_json(diag))
    rep.pop("source")
    return rep


def test_a_table_gives_the_same_report_in_any_row_order(tmp_path):
    """A table has no time structure: the same rows shuffled give the same report, every number,
    the verdict and the confidence (the noise level and the stretches used to depend on file order)."""
    header, rows = _healthy_rows(every=4)
    ref = _report(_write(tmp_path / "rig.csv", header, rows))
    assert ref["points"] == len(rows) and ref["groups"] and ref["confidence"] is not None
    for seed in (1, 2, 3):
        order = np.random.default_rng(seed).permutation(len(rows))
        shuffled = _report(_write(tmp_path / f"rig_{seed}.csv", header, [rows[i] for i in order]))
        assert shuffled == ref


def _alternating_table(tmp_path, sigma: float, n: int = 120):
    """Two operating points (100 and 300 bar) alternating row by row, motor speed with a pressure-
    proportional loss and noise of ``sigma`` rpm: file-order neighbours are always the other point."""
    rng = np.random.default_rng(5)
    dp = np.where(np.arange(n) % 2 == 0, 100.0, 300.0) + rng.normal(0.0, 0.5, n)
    temp = 50.0 + rng.normal(0.0, 0.3, n)
    speed, disp = np.full(n, 1500.0), np.full(n, 60.0)
    x = Inputs(np.arange(n, dtype=float), speed, disp, dp, temp, np.zeros(n), np.arange(n))
    y = simulate(P, x, [], MOTOR_SPEED) * (1.0 - 0.02 * dp / 300.0) + rng.normal(0.0, sigma, n)
    cols = {PUMP_SPEED: speed, PUMP_DISP: disp, DP: dp, TEMP: temp, MOTOR_SPEED: y}
    path = tmp_path / "alternating.csv"
    _write(path, list(cols), np.column_stack(list(cols.values())).tolist())
    return path


def test_a_tables_noise_comes_from_neighbours_in_operating_point_space_not_file_order(tmp_path):
    sigma = 2.0
    path = _alternating_table(tmp_path, sigma)
    spec = PointSpec({r: r for r in (*MODEL_INPUTS, MOTOR_SPEED)})
    d = gapdata.load_points(path, spec, MOTOR_SPEED)
    ctx = ctx_mod.prepare(d, P)
    assert 0.6 * sigma < ctx.sigma < 1.5 * sigma
    # What the file-order difference reads on the same rows: the gap between the two points, not noise.
    rows = np.loadtxt(path, delimiter=",", skiprows=1)
    n = len(rows)
    x = Inputs(np.arange(n, dtype=float), rows[:, 0], rows[:, 1], rows[:, 2], rows[:, 3], np.zeros(n), np.zeros(n))
    g = rows[:, 4] - simulate(P, x, [], MOTOR_SPEED)
    assert ctx_mod.noise_level(g, np.ones(n, dtype=bool), np.zeros(n, dtype=np.int64)) > 4 * sigma
    diag, _ = diagnose(d, P)
    assert diag.noise_level == ctx.sigma and diag.groups  # a 2 % loss at 300 bar is far above that noise


def test_replicates_of_one_operating_point_give_their_scatter():
    n = 60
    rng = np.random.default_rng(1)
    const = (np.full(n, v) for v in (1500.0, 60.0, 200.0, 50.0))
    x = Inputs(np.arange(n, dtype=float), *const, np.zeros(n), np.arange(n))
    g = rng.normal(0.0, 3.0, n)
    d = gapdata.GapData(x, g, np.ones(n, dtype=bool), x.dp_bar, x.dp_bar, MOTOR_SPEED, "t", "points")
    assert 1.5 < ctx_mod.table_noise_level(g, np.ones(n, dtype=bool), d) < 4.5


def test_a_table_has_no_time_order_to_withhold(tmp_path):
    header, rows = _healthy_rows(every=8)
    path = _write(tmp_path / "rig.csv", header, rows)
    with pytest.raises(ValueError, match="no time order"):
        ctx_mod.holdout_mask(gapdata.load_points(path, RIG_SPEC, FLOW), "time:last25")
    res = run_cli(
        "gap", "diagnose", str(path), "--points", str(ZEMA / "points.yaml"), "--drive", str(ZEMA / "drive.yaml"),
        "--quantity", "flow_lpm", "--holdout", "time:last25", "--out", str(tmp_path / "o"),
    )  # fmt: skip
    assert res.returncode == EX_USAGE and "no time order" in res.stderr


# The monitor's plausibility gate on table rows: units gone wrong.
def _spoiled(tmp_path, column: str, f, rows_spoiled: slice = slice(None)):
    header, rows = _healthy_rows(every=4)
    k = header.index(column)
    rows = [list(r) for r in rows]
    for r in rows[rows_spoiled]:
        r[k] = repr(f(float(r[k])))
    return _write(tmp_path / f"{column}.csv", header, rows), len(rows)


def _gap_cli(tmp_path, path, *extra):
    return run_cli(
        "gap", "diagnose", str(path), "--points", str(ZEMA / "points.yaml"), "--drive", str(ZEMA / "drive.yaml"),
        "--quantity", "flow_lpm", "--out", str(tmp_path / "o"), "--no-plots", *extra,
    )  # fmt: skip


@pytest.mark.parametrize(
    ("column", "convert", "role", "unit"),
    [
        ("ts1_c", lambda c: c + 273.15, "temp_c", "degC"),  # oil temperature in Kelvin
        ("ps1_bar", lambda b: b * 14.5038, "dp_bar", "bar"),  # pressure in psi
    ],
)
def test_a_table_in_the_wrong_unit_is_a_data_error_naming_file_and_values(tmp_path, column, convert, role, unit):
    path, n = _spoiled(tmp_path, column, convert)
    res = _gap_cli(tmp_path, path)
    assert res.returncode == EX_DATAERR, (res.returncode, res.stdout, res.stderr)
    msg = res.stderr.strip()
    assert len(msg.splitlines()) == 1 and "Traceback" not in msg
    assert str(path) in msg and f"0 of {n} operating points" in msg
    assert f"{role} " in msg and f" {unit} outside the plausible range" in msg and not NAN.search(msg)
    assert not (tmp_path / "o").exists()


def test_a_few_implausible_rows_are_left_out_and_reported(tmp_path):
    path, n = _spoiled(tmp_path, "ts1_c", lambda c: c + 273.15, slice(0, 5))
    res = _gap_cli(tmp_path, path, "--json")
    assert res.returncode == 0, res.stderr
    rep = json.loads(res.stdout)
    assert rep["points"] == n - 5 and rep["refused_points"] == 5 and "temp_c" in rep["refused_why"]
    assert "5 points" in (tmp_path / "o" / "report.md").read_text()
    assert not NAN.search(res.stdout)


def test_a_table_the_simulator_cannot_follow_is_a_data_error(tmp_path):
    """Plausible pressures that all sit at the relief valve (580 bar): nothing can be judged."""
    path, _ = _spoiled(tmp_path, "ps1_bar", lambda b: b + 400.0)
    res = _gap_cli(tmp_path, path)
    assert res.returncode == EX_DATAERR, (res.returncode, res.stderr)
    assert str(path) in res.stderr and "can be judged" in res.stderr and "relief" in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1 and not (tmp_path / "o").exists()


# A flow machine's time series: the gate's output role is the flow.
def test_the_gates_output_role_follows_the_quantity():
    assert gapdata.gate_limits_for(MOTOR_SPEED) == GateLimits()  # the reference drive: its own gates
    flow = gapdata.gate_limits_for(FLOW, GateLimits(window_s=3.0), RIG)
    assert flow.output_role == FLOW and FLOW in flow.plausible and MOTOR_SPEED not in flow.plausible
    assert flow.window_s == 3.0 and flow.min_output < 1.0  # l/min, sized for the 4.6 cm3 pump
    own = GateLimits(output_role=FLOW, min_output=0.5)
    assert gapdata.gate_limits_for(FLOW, own) is own  # a configuration for this quantity: as it is


@pytest.fixture(scope="module")
def flow_series(tmp_path_factory):
    """Two minutes at 10 Hz of a rig like ZeMA's: constant pump, pressure and oil temperature moving,
    the delivered flow reading 0.1 l/min high, with noise."""
    rng = np.random.default_rng(3)
    t = np.arange(0.0, 120.0, 0.1)
    n = len(t)
    dp = 158.0 + 2.0 * np.sin(2 * np.pi * t / 40.0) + rng.normal(0.0, 0.05, n)
    temp = np.linspace(45.0, 50.0, n)
    speed, disp = np.full(n, 1450.0), np.full(n, 4.6)
    x = Inputs(t, speed, disp, dp, temp, np.gradient(dp, t), np.zeros(n, dtype=np.int64))
    flow = simulate(RIG, x, [], FLOW) + 0.1 + rng.normal(0.0, 0.005, n)
    path = tmp_path_factory.mktemp("flow") / "flow.csv"
    write_run_csv(path, {"time_s": t, PUMP_SPEED: speed, PUMP_DISP: disp, DP: dp, TEMP: temp, FLOW: flow})
    return path


@pytest.mark.parametrize("config", [True, False], ids=["flow-config", "shipped-config"])
def test_a_flow_time_series_is_diagnosed_through_the_cli(tmp_path, flow_series, config):
    extra = ("--config", str(ZEMA / "cmcan.yaml")) if config else ()
    res = run_cli(
        "gap", "diagnose", str(flow_series), "--drive", str(ZEMA / "drive.yaml"), "--quantity", "flow_lpm",
        "--out", str(tmp_path / "o"), "--no-plots", "--json", *extra,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    rep = json.loads(res.stdout)
    assert rep["quantity"] == "flow_lpm" and rep["unit"] == "l/min" and rep["points"] > 1000
    assert rep["before"]["mean"] == pytest.approx(0.1, abs=0.02)
    assert any("output_sensor_offset" in g for g in rep["groups"]), rep["verdict"]
    assert not NAN.search(res.stdout)
    if config:  # the rig's gates, for its flow: the steady points are judged
        assert rep["where"]["regions"]["steady"]["points"] > 0.5 * rep["points"]
