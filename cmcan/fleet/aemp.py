"""The service plan as an ISO 15143-3 (AEMP 2.0) fleet snapshot, for fleet management systems.

The standard's elements cmcan can fill (``docs/fleet-telematics.md`` names the source of the element
names and types: the fleet snapshots that OEM telematics services publish in the standard's
namespace): per machine ``Equipment`` with its ``EquipmentHeader`` (``EquipmentID``: the machine id)
and ``CumulativeOperatingHours`` (``Hour`` at ``datetime``: the hours the monitor has counted, at the
time the machine was last heard). Everything else of a snapshot (make, model, serial number, PIN,
location, fuel, engine status, distance, ...) cmcan does not know and leaves out; the standard's
elements are optional but the header.

cmcan's own results are extension elements in their own namespace (:data:`NS_CMCAN`), after the
standard's, so a reader of the standard skips them: ``ConditionMonitoring`` (the plan's row: where
the state came from, warning level, CM ratio, baseline and prognosis states, hours to the warning and
to end of life p10/p50/p90, due dates, group, flags) and, while the drive's condition warns,
``FaultCode`` (the condition DTC as cmcan's DM1 sends it: SPN and FMI, severity, since when).

Pure: rows in, XML text out (:func:`document`); :func:`export` reads the data set.
"""

from __future__ import annotations

import datetime as dt
import math
import xml.etree.ElementTree as ET
from collections.abc import Mapping, Sequence
from typing import Any

from cmcan.can.j1939.dm1 import Fmi
from cmcan.config import Dm1Config
from cmcan.fleet.plan import WARNING_LEVELS, Row

NS_ISO = "http://standards.iso.org/iso/15143/-3"
NS_CMCAN = "urn:cmcan:aemp-extension:1"
VERSION = "1"  # of this document's form (the examples of the standard carry their provider's own values)
# The condition DTC of a warning level, as the DM1 of a machine with the default configuration sends
# it while the warning is not severe (docs/j1939-node.md; the data set does not record dm1.spn).
CONDITION_FMI = {"low": Fmi.BELOW_NORMAL_LEAST, "high": Fmi.ABOVE_NORMAL_LEAST}
CONDITION_SPN = Dm1Config.spn


def iso_time(t_s: float) -> str:
    """xs:dateTime in UTC, as the standard's examples write it (``2021-05-05T13:58:31Z``)."""
    return dt.datetime.fromtimestamp(t_s, dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ")


def _num(x: float | None, digits: int = 2) -> str | None:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return None
    return f"{x:.{digits}f}"


def _sub(parent: ET.Element, ns: str, tag: str, text: str | None = None, **attrib: str) -> ET.Element:
    e = ET.SubElement(parent, f"{{{ns}}}{tag}", attrib)
    if text is not None:
        e.text = text
    return e


def _hours(parent: ET.Element, tag: str, hours: Sequence[float | None]) -> None:
    """p10, p50, p90 of an hours figure: a number, ``never`` past any end, absent where there is none."""
    e = _sub(parent, NS_CMCAN, tag)
    for q, h in zip(("P10", "P50", "P90"), hours, strict=True):
        text = "never" if h is not None and math.isinf(h) else _num(h)
        if text is not None:
            _sub(e, NS_CMCAN, q, text)


def _condition(eq: ET.Element, r: Row, heard: str) -> None:
    cm = _sub(eq, NS_CMCAN, "ConditionMonitoring", datetime=heard)
    _sub(cm, NS_CMCAN, "Source", r.source)
    _sub(cm, NS_CMCAN, "Rank", str(r.rank))
    _sub(cm, NS_CMCAN, "Group", r.group)
    _sub(cm, NS_CMCAN, "WarningLevel", r.warning_level)
    if (ratio := _num(r.ratio_filt_pct, 3)) is not None:
        _sub(cm, NS_CMCAN, "CMRatioPercent", ratio)
    _sub(cm, NS_CMCAN, "BaselineState", r.baseline_state)
    _sub(cm, NS_CMCAN, "PrognosisState", r.prognosis_state)
    if r.direction:
        _sub(cm, NS_CMCAN, "Direction", r.direction)
    if (warn := _num(r.to_warning_h)) is not None:
        _sub(cm, NS_CMCAN, "HoursToWarning", warn)
    _hours(cm, "HoursToEndOfLife", r.to_eol_h)
    due = _sub(cm, NS_CMCAN, "DueDate")
    for q, d in zip(("P10", "P50", "P90"), r.due_date, strict=True):
        if d is not None:
            _sub(due, NS_CMCAN, q, d)
    if r.end_of_life:
        _sub(cm, NS_CMCAN, "EndOfLife", r.end_of_life)
    for flag in r.flags:
        _sub(cm, NS_CMCAN, "Flag", flag)


def _fault(eq: ET.Element, r: Row, since_s: float | None, heard: str) -> None:
    fmi = CONDITION_FMI.get(r.warning_level)
    if fmi is None:
        return
    f = _sub(eq, NS_CMCAN, "FaultCode", datetime=heard)
    _sub(f, NS_CMCAN, "SPN", str(CONDITION_SPN))
    _sub(f, NS_CMCAN, "FMI", str(int(fmi)))
    _sub(f, NS_CMCAN, "Severity", "warning")  # the amber lamp of cmcan's DM1
    _sub(f, NS_CMCAN, "Description", f"CM ratio {r.warning_level}: the drive's condition ({r.direction or 'wear'})")
    if since_s is not None:
        _sub(f, NS_CMCAN, "ActiveSince", iso_time(since_s))


def document(rows: Sequence[Row], since: Mapping[tuple[str, str], float], now_s: float) -> str:
    """The fleet snapshot of the plan's rows; ``since``: (machine, level) -> when it changed to it."""
    ET.register_namespace("", NS_ISO)
    ET.register_namespace("cmcan", NS_CMCAN)
    fleet = ET.Element(f"{{{NS_ISO}}}Fleet", {"version": VERSION, f"{{{NS_CMCAN}}}snapshotTime": iso_time(now_s)})
    for r in rows:
        eq = _sub(fleet, NS_ISO, "Equipment")
        head = _sub(eq, NS_ISO, "EquipmentHeader")
        _sub(head, NS_ISO, "EquipmentID", r.machine)
        heard = r.last_heard if r.last_heard.endswith("Z") else r.last_heard.replace("+00:00", "Z")
        hours = _sub(eq, NS_ISO, "CumulativeOperatingHours", datetime=heard)
        _sub(hours, NS_ISO, "Hour", _num(r.operating_h) or "0.00")
        _condition(eq, r, heard)
        if r.warning_level in WARNING_LEVELS:
            _fault(eq, r, since.get((r.machine, r.warning_level)), heard)
    ET.indent(fleet)
    return '<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(fleet, encoding="unicode") + "\n"


_SINCE = """
    SELECT machine, to_level, max(time_s) FROM (
        SELECT machine, time_s, to_level FROM events
        UNION ALL SELECT machine, time_s, to_level FROM uplink_events WHERE type = 'level_change')
    WHERE time_s <= ? AND to_level IN ('low', 'high') GROUP BY machine, to_level"""


def export(root: Any, at_s: float | None, now_s: float) -> tuple[str, list[Row]]:
    """The snapshot of the data set's plan as of ``at_s`` (None: all of it), and the plan's rows."""
    from cmcan.fleet import plan
    from cmcan.fleet.query import read

    at = math.inf if at_s is None else at_s

    def snapshot(con: Any) -> tuple[list[Any], dict[tuple[str, str], float]]:
        rows = plan.plan(plan.facts(con, at), now_s)
        return rows, {(m, lv): float(t) for m, lv, t in con.execute(_SINCE, [at]).fetchall()}

    rows, since = read(root, snapshot, {"timeline", "events", "uplink_summaries", "uplink_events"})
    return document(rows, since, now_s), rows
