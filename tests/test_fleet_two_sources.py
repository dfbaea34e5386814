"""One data set, two sources: the plan, the query and the report read the rows of the machines' logs
and of their gateways' uplink together. A machine known only from its uplink is planned from its
summaries; a machine in both is one row, from the source heard last; each row says where its state
came from and how old it is."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

pytest.importorskip("pyarrow")
pytest.importorskip("duckdb")

from cmcan.fleet import dataset as ds
from cmcan.fleet import uplinkstore as store
from cmcan.fleet.plan import LOGS, UPLINK, Facts, merge
from cmcan.fleet.uplinkrows import Batch, Seen, parse
from cmcan.uplink.records import dumps, envelope
from tests.test_fleet_plan import DAY_S, NO, ROWS, T0_S, TR, _log


def summary(machine: str, seq: int, t_s: float, level: str = "ok", op_h: float = 0.0, **extra) -> bytes:
    body = {
        "level": level,
        "reason": "none",
        "ratio_filt_pct": 99.1,
        "time_in_level_total_s": {"ok": op_h * 3600.0, "low": 0.0, "high": 0.0, "fault": 0.0},
        **extra,
    }
    return envelope(machine, "a1b2", seq, "summary", t_s, False, dumps(body)).encode()


def ingest(root: Path, messages: list[tuple[str, bytes]]) -> None:
    """Two batches (every other message); the first folded into the machine/day partitions, the
    second not: the readers take both layouts as one."""
    for k in (0, 1):
        b = Batch()
        for tp, body in messages[k::2]:
            assert b.add(parse(tp, body, "cmcan", T0_S), Seen(), T0_S, None) == "new"
        first = store.commit_batch(root, b, store.key_of(k + 1), T0_S)
        if k == 0:
            assert first is not None
            store.fold(root, [first], store.key_of(3), T0_S + 100 * DAY_S)


PROGNOSIS = {"state": "trend", "direction": "low", "to_warning_h": 5.0, "to_eol_h": [12.0, 20.0, "never"]}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    root = ds.open_dataset(tmp_path_factory.mktemp("two") / "ds", create=True)
    for day in range(4):
        _log(root, "m-wear", day, ["ok"] * ROWS, [TR] * ROWS, [60.0 - 8 * day] * ROWS)
        _log(root, "m-ok", day, ["ok"] * ROWS, [NO] * ROWS, [math.nan] * ROWS)
    msgs = [  # m-wear: an uplink summary older than its logs; m-ok: newer ones; m-gw: the uplink only
        ("cmcan/m-wear/summary", summary("m-wear", 1, T0_S + 1 * DAY_S, "high")),
        ("cmcan/m-ok/summary", summary("m-ok", 1, T0_S + 5 * DAY_S, op_h=50.0)),
        ("cmcan/m-ok/summary", summary("m-ok", 2, T0_S + 6 * DAY_S, "low", 58.0, prognosis=PROGNOSIS)),
    ]
    for i in range(6):
        base = {"state": "learning", "learned_h": i * 2.0, "coverage_pct": 10.0, "distance_lpm": 0.1}
        msgs.append(("cmcan/m-gw/summary", summary("m-gw", i + 1, T0_S + i * DAY_S, op_h=6.0 * i, baseline=base)))
    event = {"type": "level_change", "from": "ok", "to": "low", "reason": "ratio_low"}
    msgs.append(("cmcan/m-gw/event", envelope("m-gw", "a1b2", 7, "event", T0_S + 5.5 * DAY_S, False, dumps(event))))
    ingest(root, [(tp, b if isinstance(b, bytes) else b.encode()) for tp, b in msgs])
    return root


def test_the_plan_reads_both_sources_and_counts_each_machine_once(dataset, capsys):
    from cmcan.cli import main

    assert main(["fleet", "plan", str(dataset), "--json", "--at", "2026-01-08"]) == 0
    rows = {r["machine"]: r for r in json.loads(capsys.readouterr().out)["machines"]}
    assert sorted(rows) == ["m-gw", "m-ok", "m-wear"]
    wear, ok, gw = rows["m-wear"], rows["m-ok"], rows["m-gw"]
    assert (wear["source"], wear["warning_level"], wear["group"]) == (LOGS, "ok", "trend")  # its logs are newer
    assert (ok["source"], ok["warning_level"], ok["prognosis_state"], ok["direction"]) == (
        UPLINK,
        "low",
        "trend",
        "low",
    )
    assert ok["to_eol_h"] == [12.0, 20.0, None] and "eol_not_reached" in ok["flags"]
    assert ok["end_of_life"] == "wear: the CM ratio at 90 %"  # what only its logs know is kept
    assert ok["last_heard_days"] == pytest.approx(1.0)
    # known from its uplink only: its latest summary's baseline, its level changed by an event after it
    assert (gw["source"], gw["baseline_state"], gw["warning_level"], gw["group"]) == (
        UPLINK,
        "learning",
        "low",
        "warning_now",
    )
    assert gw["operating_h"] == pytest.approx(30.0) and gw["utilisation_h_per_day"] == pytest.approx(6.0)
    assert gw["last_heard_days"] == pytest.approx(1.5)  # its event, half a day after its last summary
    assert main(["fleet", "plan", str(dataset), "--at", "2026-01-08"]) == 0
    assert "(2 d, uplink)" in capsys.readouterr().out


def test_the_query_has_the_uplinks_tables(dataset, capsys):
    from cmcan.cli import main

    sql = "SELECT machine, count(*) AS n, max(operating_total_h) AS h FROM uplink_summaries GROUP BY 1 ORDER BY 1"
    assert main(["fleet", "query", str(dataset), sql, "--format", "json"]) == 0
    got = json.loads(capsys.readouterr().out)
    assert [(r["machine"], r["n"]) for r in got] == [("m-gw", 6), ("m-ok", 2), ("m-wear", 1)]
    assert main(["fleet", "query", str(dataset), "SELECT count(*) AS n FROM uplink_quarantine", "--format", "csv"]) == 0
    assert capsys.readouterr().out == "n\n0\n"


@pytest.mark.parametrize("folded", [True, False])
def test_a_damaged_uplink_file_is_named_not_read(dataset, tmp_path, capsys, folded):
    import shutil

    from cmcan.cli import main

    copy = tmp_path / "ds"
    shutil.copytree(dataset, copy)
    live = store.committed_files(copy)[0]["uplink_summaries"]
    f = next(p for m, p in live if (m is not None) == folded)  # in a partition, or a batch's flat file
    f.write_bytes(f.read_bytes()[:-8] + b"\0" * 8)
    assert main(["fleet", "query", str(copy), "SELECT count(*) FROM uplink_summaries"]) == 65
    assert f.name in capsys.readouterr().err


def test_merge_takes_the_source_heard_last():
    log = Facts("m", last_heard_s=10.0, operating_h=5.0, level="ok", fit="does_not_fit", end_of_life="eol")
    newer = Facts("m", last_heard_s=11.0, operating_h=7.0, level="low", source=UPLINK)
    older = Facts("m", last_heard_s=9.0, operating_h=7.0, level="low", source=UPLINK)
    (got,) = merge([log], [newer])
    assert (got.source, got.level, got.fit, got.end_of_life) == (UPLINK, "low", "does_not_fit", "eol")
    assert merge([log], [older]) == [log]
    assert merge([], [older]) == [older]


def test_the_report_ranks_the_uplinks_machines_with_the_others(dataset, tmp_path):
    pytest.importorskip("matplotlib")
    from cmcan.fleet.report import write_report

    out = tmp_path / "r.html"
    write_report(dataset, out, 50.0, 50)
    text = out.read_text()
    assert "m-gw" in text and text.count(", uplink)") == 2  # m-gw and m-ok: their latest state is their uplink's


# -- the ISO 15143-3 (AEMP 2.0) fleet snapshot --------------------------------------------------------

# The standard's elements as the open examples have them (docs/fleet-telematics.md names them): the
# fleet snapshots OEM telematics services serve in the standard's namespace. Element -> its parent and
# the type of its text (None: children only).
ISO = "http://standards.iso.org/iso/15143/-3"
STANDARD = {
    "Fleet": (None, None),
    "Links": ("Fleet", None),
    "rel": ("Links", "string"),
    "href": ("Links", "string"),
    "Equipment": ("Fleet", None),
    "EquipmentHeader": ("Equipment", None),
    **{
        k: ("EquipmentHeader", "string")
        for k in ("UnitInstallDateTime", "OEMName", "Model", "Make", "EquipmentID", "SerialNumber", "PIN")
    },
    "Location": ("Equipment", None),
    "Latitude": ("Location", "decimal"),
    "Longitude": ("Location", "decimal"),
    "CumulativeOperatingHours": ("Equipment", None),
    "Hour": ("CumulativeOperatingHours", "decimal"),
    "EngineStatus": ("Equipment", None),
    "Running": ("EngineStatus", "boolean"),
}
DATETIME_ATTR = {"Location", "CumulativeOperatingHours", "EngineStatus"}


def check_snapshot(text: str) -> list[str]:
    """What in a snapshot is not the standard's element names and types (its own namespace), or an
    extension that is not in a namespace of its own after the standard's elements."""
    import datetime as dt
    import xml.etree.ElementTree as ET

    problems = []
    root = ET.fromstring(text)

    def walk(e: ET.Element, parent: str | None) -> None:
        ns, _, name = e.tag[1:].partition("}")
        if ns != ISO:
            if not ns or parent != "Equipment":
                problems.append(f"{e.tag}: an extension must be in its own namespace, in Equipment")
            return
        if STANDARD.get(name, (0,))[0] != parent:
            problems.append(f"{name} under {parent}: not the standard's place")
            return
        kind = STANDARD[name][1]
        value = (e.text or "").strip()
        try:
            if kind == "decimal":
                float(value)
            elif kind == "boolean" and value not in ("true", "false"):
                raise ValueError(value)
        except ValueError:
            problems.append(f"{name}: {value!r} is not a {kind}")
        if name in DATETIME_ATTR:
            stamp = e.get("datetime", "")
            if not (stamp.endswith("Z") and dt.datetime.fromisoformat(stamp[:-1] + "+00:00")):
                problems.append(f"{name}/@datetime: {stamp!r} is not an xs:dateTime in UTC")
        children = list(e)
        if name == "Equipment":
            if not children or children[0].tag != f"{{{ISO}}}EquipmentHeader":
                problems.append("Equipment: EquipmentHeader must come first")
            seen_ext = False
            for c in children:
                seen_ext |= not c.tag.startswith(f"{{{ISO}}}")
                if seen_ext and c.tag.startswith(f"{{{ISO}}}"):
                    problems.append(f"{c.tag}: a standard element after an extension")
        for c in children:
            walk(c, name)

    walk(root, None)
    if root.get("version") is None:
        problems.append("Fleet/@version missing")
    return problems


REFERENCE = f"""<Fleet xmlns="{ISO}" version="0"><Links><rel>self</rel><href>https://x/Fleet/1</href></Links>
<Equipment><EquipmentHeader><OEMName>O</OEMName><Model>5075</Model><EquipmentID>e1</EquipmentID>
<SerialNumber>1</SerialNumber><PIN>P1</PIN></EquipmentHeader>
<Location datetime="2021-05-05T13:58:31Z"><Latitude>50.95</Latitude><Longitude>12.46</Longitude></Location>
<CumulativeOperatingHours datetime="2021-05-05T13:58:31Z"><Hour>1937.23</Hour></CumulativeOperatingHours>
<EngineStatus datetime="2021-05-05T13:58:31Z"><Running>false</Running></EngineStatus></Equipment></Fleet>"""


def test_the_check_accepts_the_standards_shape_and_names_what_is_not():
    assert check_snapshot(REFERENCE) == []
    bad = REFERENCE.replace("<Hour>1937.23</Hour>", "<Hour>many</Hour><Hours>1</Hours>")
    bad = bad.replace('datetime="2021-05-05T13:58:31Z"><Lat', 'datetime="yesterday"><Lat')
    assert (
        check_snapshot(bad)
        == [
            "Location/@datetime: 'yesterday' is not an xs:dateTime in UTC",
            "Hour: 'many' is not a decimal",
            "Hours under CumulativeOperatingHours: not the standard's place",
        ]
        or len(check_snapshot(bad)) == 3
    )


def test_the_plan_as_an_aemp_fleet_snapshot(dataset, tmp_path, capsys):
    import xml.etree.ElementTree as ET

    from cmcan.cli import main
    from cmcan.fleet.aemp import CONDITION_SPN, NS_CMCAN

    out = tmp_path / "fleet.xml"
    assert main(["fleet", "plan", str(dataset), "--at", "2026-01-08", "--aemp", str(out), "--json"]) == 0
    plan = {r["machine"]: r for r in json.loads(capsys.readouterr().out)["machines"]}
    text = out.read_text()
    assert check_snapshot(text) == []
    root = ET.fromstring(text)
    c = {"i": ISO, "c": NS_CMCAN}
    got = {}
    for eq in root.findall("i:Equipment", c):
        machine = eq.find("i:EquipmentHeader/i:EquipmentID", c).text
        got[machine] = eq
        cm = eq.find("c:ConditionMonitoring", c)
        assert cm.find("c:WarningLevel", c).text == plan[machine]["warning_level"]
        assert cm.find("c:Source", c).text == plan[machine]["source"]
        hours = float(eq.find("i:CumulativeOperatingHours/i:Hour", c).text)
        assert hours == pytest.approx(plan[machine]["operating_h"], abs=0.01)
    assert list(got) == list(plan)  # in the plan's order
    fault = got["m-gw"].find("c:FaultCode", c)  # warns low since its level change
    assert (fault.find("c:SPN", c).text, fault.find("c:FMI", c).text) == (str(CONDITION_SPN), "17")
    assert fault.find("c:ActiveSince", c).text == "2026-01-06T12:00:00Z"
    assert got["m-wear"].find("c:FaultCode", c) is None
    eol = got["m-ok"].find("c:ConditionMonitoring/c:HoursToEndOfLife", c)
    assert [e.text for e in eol] == ["12.00", "20.00", "never"]
    assert main(["fleet", "plan", str(dataset), "--aemp", str(out)]) == 73  # not overwritten without --force
