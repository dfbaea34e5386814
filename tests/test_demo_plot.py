"""The demo's figure and folder: the whole fall of the ratio at each failure on the axis, a legend for
every kind of line, lead times that do not sit on a failure line, a title naming the machine's bus, and
an earlier demo's output kept."""

from __future__ import annotations

import numpy as np
import pytest

from cmcan import config as cfgmod
from cmcan.cli.demo import DEFAULT_OUT, out_dir
from cmcan.cli.errors import EX_CANTCREAT
from cmcan.demo import DemoResult, frames_kind, title_of
from cmcan.errors import CmcanError
from cmcan.monitor.warnings import Thresholds
from cmcan.plots import demo_figure, plot_demo
from tests.conftest import ROOT, run_cli

TH = Thresholds()


def _result() -> DemoResult:
    """The demo's shape: flat at 100 %, two wear failures falling to about 43 % and a misposition
    rising to 111 % before its failure, each warned of in time."""
    h = np.arange(0.0, 550.0, 0.5)
    r = np.full_like(h, 100.0)
    for start, fail in ((240.0, 290.0), (315.0, 365.0)):
        m = (h >= start) & (h <= fail)
        r[m] = 100.0 - 57.0 * ((h[m] - start) / (fail - start)) ** 3
    m = (h >= 515.0) & (h <= 535.0)
    r[m] = 100.0 + 11.0 * (h[m] - 515.0) / 20.0
    failures = [
        {"component": "motor", "kind": "wear", "fail_h": 290.0, "first_warning_h": 261.0, "level": "low"},
        {"component": "pump", "kind": "wear", "fail_h": 365.0, "first_warning_h": 335.5, "level": "low"},
        {"component": "motor", "kind": "misposition", "fail_h": 535.0, "first_warning_h": 520.5, "level": "high"},
    ]
    for f in failures:
        f["lead_h"] = f["fail_h"] - f["first_warning_h"]
    return DemoResult(
        "run_to_failure",
        "virtual:x",
        "config/cmcan.yaml",
        "11-bit identifiers",
        1,
        1,
        1.0,
        failures=failures,
        ratio_h=h.tolist(),
        ratio_pct=r.tolist(),
    )


def test_the_demo_figure_shows_each_fall_and_explains_every_line(tmp_path):
    res = _result()
    spec = demo_figure(res, TH, "t")
    lo, hi = spec.ylim
    assert lo < min(res.ratio_pct) and max(res.ratio_pct) < hi  # the fall to 43 % and the rise to 111 %
    assert lo < TH.low_pct < TH.high_pct < hi and spec.band == (TH.low_pct, TH.high_pct)
    assert [x for x, _ in spec.failures] == [290.0, 365.0, 535.0]
    assert all(f"{f['fail_h']:g} h" in label for f, (_, label) in zip(res.failures, spec.failures, strict=True))
    legend = " | ".join(spec.legend)
    for kind in ("CM ratio", "ok band", "low threshold", "high threshold", "failure", "first low warning"):
        assert kind in legend, kind
    assert "first high warning" in legend and "lead time" in legend
    h, r = np.asarray(res.ratio_h), np.asarray(res.ratio_pct)
    for lead in spec.leads:
        assert lead.text == f"lead {lead.fail_h - lead.warning_h:.0f} h"
        # the text ends at the warning line, on the far side from the failure line
        assert lead.text_x == lead.warning_h < lead.fail_h and lead.ha == "right"
        # ... at a height the ratio is not at, from well before the warning to the failure
        near = r[(h >= lead.warning_h - 30.0) & (h <= lead.fail_h)]
        assert (near < lead.y - 1).all() if lead.level == "low" else (near > lead.y + 1).all()
    drawn = plot_demo(res, TH, tmp_path / "demo.png", "t")
    assert drawn == spec and (tmp_path / "demo.png").stat().st_size > 20_000


def test_the_demo_title_names_the_configuration_and_its_bus():
    plain = cfgmod.load(None)
    j1939 = cfgmod.load(ROOT / "config" / "j1939-example.yaml")
    assert frames_kind(plain) == "11-bit identifiers"
    assert frames_kind(j1939).startswith("J1939") and "0x8C" in frames_kind(j1939)
    titles = set()
    for cfg in (plain, j1939):
        res = _result()
        res.config, res.frames = cfg.source, frames_kind(cfg)
        titles.add(title_of(res))
    assert len(titles) == 2 and any("j1939-example.yaml" in t and "J1939" in t for t in titles)


def test_an_earlier_demo_is_kept(tmp_path, monkeypatch):
    """The README's one command (`cmcan demo`) runs again into a new folder; a folder named with
    --out-dir that holds an earlier demo is refused without --force."""
    fast = ("--burst-s", "1", "--every-min", "600")  # a sparse time-lapse: the folder is what is tested
    res = run_cli("demo", *fast, cwd=tmp_path)
    assert res.returncode in (0, 1), res.stderr  # (the checks need the full sampling)
    first = tmp_path / DEFAULT_OUT / "demo.png"
    before = first.read_bytes()
    res = run_cli("demo", *fast, "--no-plot", cwd=tmp_path)
    assert res.returncode in (0, 1), res.stderr
    assert f"into {DEFAULT_OUT}-2/" in res.stdout and (tmp_path / f"{DEFAULT_OUT}-2" / "state").is_dir()
    res = run_cli("demo", *fast, "--out-dir", DEFAULT_OUT, cwd=tmp_path)
    assert res.returncode == EX_CANTCREAT and "--force" in res.stderr and "demo.png" in res.stderr
    assert first.read_bytes() == before
    monkeypatch.chdir(tmp_path)
    assert out_dir(None, False).name == f"{DEFAULT_OUT}-3"
    assert out_dir(DEFAULT_OUT, True).name == DEFAULT_OUT  # asked to overwrite
    (tmp_path / "afile").write_text("x")
    with pytest.raises(CmcanError, match="not a folder"):
        out_dir("afile", True)


def test_the_demo_figure_shades_the_learning_of_the_machines_own_baseline(tmp_path):
    res = _result()
    assert demo_figure(res, TH, "t").learning is None  # no CM_BASELINE seen: nothing shaded
    res.baseline = [(0.0, "learning"), (18.4, "monitoring")]
    spec = demo_figure(res, TH, "t")
    assert spec.learning == (0.0, 18.4)
    assert any("learning its own baseline (18 h" in x for x in spec.legend)
    assert plot_demo(res, TH, tmp_path / "demo.png", "t") == spec
    res.baseline = [(0.0, "learning")]  # still learning at the end: no phase that ended
    assert demo_figure(res, TH, "t").learning is None


def _with_prognosis(res: DemoResult) -> list[tuple[float, str, float, float, float]]:
    """CM_PROGNOSIS as the demo decodes it, every quarter hour: none (hours 0, as the frame carries
    them) but over each wear: a trend from 39 h before the failure, p50 5 % off the truth with a
    +-15 % band, the motor's estimate carried on for an hour past its failure (until its replacement
    restarts it) and a lost trend on the pump between 345 and 347 h; the misposition has none."""
    seen = []
    for h in np.arange(0.0, 550.0, 0.25).tolist():
        state, p50 = "none", 0.0
        if 251.0 <= h <= 291.0:
            state, p50 = "trend", 1.05 * max(290.0 - h, 0.0)
        elif 326.0 <= h <= 365.0 and not 345.0 < h < 347.0:
            state, p50 = ("imminent" if h > 350.0 else "trend"), 0.95 * (365.0 - h)
        seen.append((h, state, 0.85 * p50, p50, 1.15 * p50))
    res.prognosis = seen
    return seen


def test_the_demo_figure_shows_the_estimate_and_its_band_over_each_failing_stretch(tmp_path):
    res = _result()
    assert demo_figure(res, TH, "t").prognosis_ylim is None  # no CM_PROGNOSIS seen: no panel
    seen = _with_prognosis(res)
    spec = demo_figure(res, TH, "t")
    motor, pump, mis = spec.prognosis
    assert [s.label for s in spec.prognosis] == ["motor wear", "pump wear", "motor misposition"]
    # from the first estimate (before the first warning) to the failure; the pump's not from the
    # motor's estimate carried past its failure
    assert (motor.start_h, motor.fail_h) == (251.0, 290.0) and (pump.start_h, pump.fail_h) == (326.0, 365.0)
    # no estimate before the misposition: its stretch from the first warning, nothing drawn
    assert (mis.start_h, mis.fail_h, mis.runs, mis.band_points) == (520.5, 535.0, (), 0)
    none_h = {x[0] for x in seen if x[1] == "none"}
    for s in (motor, pump):
        points = [p for run in s.runs for p in run]
        assert s.band_points == len(points) > 100  # a band over each wear failure's stretch ...
        hours = [p[0] for p in points]
        assert min(hours) == s.start_h and s.fail_h - 0.5 < max(hours) <= s.fail_h  # ... all of it
        assert all(p10 <= p50 <= p90 for _, p10, p50, p90 in points)
        assert not none_h & set(hours)  # nothing drawn where the state is none
    assert len(motor.runs) == 1 and len(pump.runs) == 2  # the band broken where the trend was lost
    assert not any(345.0 < p[0] < 347.0 for run in pump.runs for p in run)
    lo, hi = spec.prognosis_ylim
    assert lo == 0.0 and 39.0 < hi < 2 * 39.0  # the longest stretch's truth and band in view
    assert "p10-p90" in spec.prognosis_legend and any("true hours left" in x for x in spec.prognosis_legend)
    assert plot_demo(res, TH, tmp_path / "demo.png", "t") == spec and (tmp_path / "demo.png").stat().st_size > 20_000


def test_a_saturated_or_lost_estimate_does_not_stretch_the_panel():
    """The frame's 4000 h (far, or never) stays off the scale; a demo where no estimate and no warning
    came before a failure has no stretch for it."""
    res = _result()
    seen = _with_prognosis(res)
    res.prognosis = [(h, s, *((4000.0,) * 3 if s != "none" and h < 260.0 else (a, b, c))) for h, s, a, b, c in seen]
    assert demo_figure(res, TH, "t").prognosis_ylim[1] <= 2.2 * 39.0
    res.failures[2]["first_warning_h"] = None
    assert [s.label for s in demo_figure(res, TH, "t").prognosis] == ["motor wear", "pump wear"]
