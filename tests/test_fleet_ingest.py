"""``cmcan fleet ingest``'s pure parts and its commit: the payload parser against hostile input (never
a crash, never an unsafe name, each refusal with its reason), deduplication by id, a batch committed
before any of its messages is acknowledged, a commit cut short leaving nothing behind, the command
line's broker URL checked by the uplink's own rules. Against a real broker:
``tests/test_fleet_ingest_integration.py``."""

from __future__ import annotations

import json
import math
from pathlib import Path
from types import SimpleNamespace

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

pytest.importorskip("pyarrow")

import pyarrow.parquet as pq

from cmcan.errors import CmcanError, Kind
from cmcan.fleet import dataset as ds
from cmcan.fleet import ingest as ig
from cmcan.fleet import uplinkstore as store
from cmcan.fleet.uplinkrows import (
    MAX_PAYLOAD_BYTES,
    UPLINK_QUARANTINE,
    Batch,
    Message,
    Refusal,
    Seen,
    parse,
)
from cmcan.uplink.records import envelope
from tests.helpers import systemd_verify

T0 = 1767225600.0


def payload(machine: str = "wl-1", seq: int = 1, kind: str = "summary", stream: str = "7d58", **body) -> bytes:
    base = {"level": "ok", "reason": "none", "ratio_filt_pct": 99.5} if kind == "summary" else {}
    body_json = json.dumps({**base, **body}) if (base or body) else "{}"
    return envelope(machine, stream, seq, kind, T0 + 900 * seq, False, body_json).encode()


def topic(machine: str = "wl-1", kind: str = "summary") -> str:
    return f"cmcan/{machine}/{kind}"


# -- the parser -----------------------------------------------------------------------------------------


def test_a_summary_as_the_uplink_publishes_it_parses_into_its_row():
    body = {
        "level": "low",
        "reason": "ratio_low",
        "ratio_filt_pct": 97.5,
        "evaluated_total_h": 12.5,
        "baseline": {"state": "monitoring", "learned_h": 4.0, "coverage_pct": 80.0, "distance_lpm": 0.1},
        "prognosis": {"state": "trend", "direction": "low", "to_warning_h": 0.0, "to_eol_h": [10.0, 20.0, "never"]},
    }
    m = parse(topic(), payload(seq=3, **body), "cmcan", T0)
    assert isinstance(m, Message), m
    assert (m.table, m.machine, m.day, m.dedup) == ("uplink_summaries", "wl-1", "2026-01-01", ("wl-1/7d58", 3))
    r = m.row
    assert (r["id"], r["level"], r["baseline_state"], r["prognosis_state"]) == ("7d58-3", "low", "monitoring", "trend")
    assert (r["prognosis_to_eol_p10_h"], r["prognosis_to_eol_p90_h"]) == (10.0, math.inf)
    assert json.loads(r["payload"])["evaluated_total_h"] == 12.5


def test_an_integer_too_large_for_a_float_reads_as_no_number():
    """(It raised OverflowError, so one such message stopped the ingest at every redelivery.)"""
    huge = 10**400
    prognosis = {"state": "trend", "to_warning_h": huge, "to_eol_h": [1.0, huge, "never"]}
    m = parse(topic(), payload(ratio_filt_pct=huge, warning_count=huge, prognosis=prognosis), "cmcan", T0)
    assert isinstance(m, Message), m
    r = m.row
    assert (r["ratio_filt_pct"], r["warning_count"], r["prognosis_to_warning_h"]) == (None, None, None)
    assert (r["prognosis_to_eol_p10_h"], r["prognosis_to_eol_p50_h"], r["prognosis_to_eol_p90_h"]) == (
        1.0,
        None,
        math.inf,
    )
    assert parse(topic(), payload(ratio_filt_pct=10**300), "cmcan", T0).row["ratio_filt_pct"] == 1e300  # a float still


@pytest.mark.parametrize(
    ("tp", "body", "reason"),
    [
        (topic(), b"not json", "not JSON"),
        (topic(), b"x" * (MAX_PAYLOAD_BYTES + 1), "more than"),
        (topic(), b"[" * 100_000 + b"]" * 100_000, "nested too deep"),
        (topic(), b"\xff\xfe", "not UTF-8"),
        (topic(), b'{"schema": 1, "schema": 1}', "repeats the key"),
        (topic(), b'{"schema": NaN}', "NaN"),
        (topic(), b"[1]", "expected an object"),
        ("cmcan/../summary", payload(".."), "not a safe name"),
        ("cmcan/wl-1/secrets", payload(), "none of"),
        ("other/wl-1/summary", payload(), "topic is not"),
        (topic("wl-2"), payload("wl-1"), "differs from the topic"),
        (topic(), payload().replace(b'"schema":1', b'"schema":7'), "newer than this ingest reads"),
        (topic(), payload().replace(b'"schema":1', b'"schema":true'), "field 'schema'"),
        (topic(), payload().replace(b'"id":"7d58-1"', b'"id":"../../x-1"'), "is not <stream>-<seq>"),
        (topic(), payload().replace(b'"id":"7d58-1"', b'"id":"7d58-2"'), "does not end in its seq"),
        (topic(), payload(level="purple"), "field 'level'"),
        (topic(), payload().replace(b'"t_s":1767226500.0', b'"t_s":1e300'), "between 1970 and 9999"),
        (topic(), payload().replace(b'"t_s":1767226500.0', b'"t_s":1' + b"0" * 400), "between 1970 and 9999"),
        (topic("wl-1", "dropped"), payload(kind="dropped", reason="full", entries=10**30), "beyond 64 bits"),
    ],
)
def test_hostile_payloads_are_refused_with_their_reason(tp, body, reason):
    r = parse(tp, body, "cmcan", T0)
    assert isinstance(r, Refusal), r
    assert reason in r.reason
    assert len(r.topic) <= 120 and "\n" not in r.reason


_json = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=8),
    lambda c: st.lists(c, max_size=3) | st.dictionaries(st.text(max_size=6), c, max_size=3),
    max_leaves=8,
)
_FIELDS = ("schema", "kind", "machine_id", "id", "seq", "t_s", "late", "level", "type", "state", "reason")


@st.composite
def hostile(draw):
    """A valid message with some of its topic and fields replaced by anything, or bytes."""
    machine = draw(st.sampled_from(["wl-1"] * 6 + ["..", "a/b", "x" * 101, "ok.1", "\u00e9", "a\n"]))
    kind = draw(st.sampled_from(["summary", "event", "dropped", "status"] * 3 + ["health"]))
    if draw(st.booleans()) and draw(st.booleans()):
        return f"cmcan/{machine}/{kind}", draw(st.binary(max_size=64))
    p = json.loads(payload("wl-1", draw(st.integers(0, 10**6)), kind if kind != "health" else "summary"))
    if kind == "status":
        p = {"schema": 1, "kind": "status", "machine_id": "wl-1", "state": "online"}
    for f in draw(st.lists(st.sampled_from(_FIELDS), max_size=1)):
        p[f] = draw(_json)
    return f"cmcan/{machine}/{kind}", json.dumps(p).encode()


def test_the_parser_never_raises_and_names_only_safe_paths():
    reached: dict[str, int] = {}

    @settings(max_examples=300, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
    @given(hostile())
    def check(msg):
        tp, body = msg
        r = parse(tp, body, "cmcan", T0)
        if isinstance(r, Message):
            assert ds.MACHINE_RE.fullmatch(r.machine) and len(r.day) == 10
            assert ds.partition(Path("/d"), r.table, r.machine, r.day).resolve().is_relative_to("/d")
            reached["ok"] = reached.get("ok", 0) + 1
        else:
            assert isinstance(r.reason, str) and r.reason
            key = r.reason.split(" ")[0] + (" " + r.reason.split("'")[1] if "'" in r.reason else "")
            reached[key] = reached.get(key, 0) + 1

    check()
    # the interesting cases were reached, not only bytes that never parse
    assert reached.get("ok", 0) > 10
    for what in ("payload", "machine", "topic", "field kind", "field id", "field seq", "field t_s", "field schema"):
        assert any(k.startswith(what) for k in reached), (what, sorted(reached))


# -- deduplication ------------------------------------------------------------------------------------


@settings(max_examples=100, deadline=None)
@given(st.lists(st.tuples(st.sampled_from(["a", "b"]), st.integers(0, 40)), max_size=80))
def test_seen_holds_exactly_what_was_added_as_few_ranges(items):
    s = Seen()
    for it in items:
        s.add(it)
    for stream in ("a", "b"):
        for seq in range(-1, 42):
            assert ((stream, seq) in s) == ((stream, seq) in set(items))
        rs = s.ranges.get(stream, [])
        assert all(rs[i][1] + 1 < rs[i + 1][0] for i in range(len(rs) - 1))  # disjoint, not adjacent
    again = Seen()
    again.merge(json.loads(json.dumps({"ranges": s.ranges, "keys": []})))
    assert again.ranges == s.ranges


def test_a_batch_keeps_one_copy_and_quarantines_a_copy_with_other_content():
    seen, b = Seen(), Batch()
    first = parse(topic(), payload(seq=1), "cmcan", T0)
    late_copy = parse(topic(), payload(seq=1).replace(b'"late":false', b'"late":true'), "cmcan", T0)
    other = parse(topic(), payload(seq=1, level="low"), "cmcan", T0)
    clone = parse(topic("wl-2"), payload("wl-2", seq=1), "cmcan", T0)  # a cloned gateway: same stream
    bad = parse(topic(), b"junk", "cmcan", T0)
    outcome = [b.add(m, seen, T0, (i, 1)) for i, m in enumerate([first, late_copy, other, clone, bad, bad])]
    assert outcome == ["new", "duplicate", "quarantined", "new", "quarantined", "duplicate"]
    assert [q["reason"][:24] for q in b.quarantine] == ["id 7d58-1 arrived before", "payload is not JSON (Exp"]
    assert len(b.acks) == 6
    b.committed_into(seen)
    b2 = Batch()  # after the commit: copies redelivered by the broker are duplicates, a new conflict is not
    third = parse(topic(), payload(seq=1, level="high"), "cmcan", T0)
    outcome = [b2.add(m, seen, T0, None) for m in (first, other, bad, third)]
    assert outcome == ["duplicate", "duplicate", "duplicate", "quarantined"]


# -- the commit ---------------------------------------------------------------------------------------


def a_batch(n: int = 5, machines: tuple[str, ...] = ("wl-1", "wl-2")) -> Batch:
    b, seen = Batch(), Seen()
    for m in machines:
        for seq in range(1, n + 1):
            b.add(parse(topic(m), payload(m, seq), "cmcan", T0), seen, T0, (seq, 1))
    b.add(parse(topic("wl-1", "event"), b"{}", "cmcan", T0), seen, T0, (99, 1))
    return b


class FakeClient:
    """Records acknowledgements; each must find its batch committed (record and files in place)."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.acked: list[int] = []

    def ack(self, mid: int, _qos: int) -> None:
        records = store.record_paths(self.root)
        assert records, "acknowledged before the commit record was in place"
        for r in records:
            for f in json.loads(ds.read_record(r)[ds.FILES]):
                assert store.place_of(self.root, f).is_file()
        self.acked.append(mid)


def ingest_on(root: Path) -> ig.Ingest:
    m = SimpleNamespace(max_inflight=100, topic_prefix="cmcan")
    return ig.Ingest(root, m, Seen())  # type: ignore[arg-type]


def test_a_batch_is_committed_before_its_messages_are_acknowledged(tmp_path):
    root = ds.open_dataset(tmp_path / "ds", create=True)
    ing = ingest_on(root)
    ing.client, ing.connected = FakeClient(root), True
    ing.batch = a_batch()
    ing.flush()
    assert sorted(ing.client.acked) == sorted([*range(1, 6)] * 2 + [99])
    seen, records = store.load_seen(root)
    assert len(records) == 1 and ("wl-2/7d58", 5) in seen and ("wl-2/7d58", 6) not in seen
    # one file per table, whatever the number of machines: the machine and day are columns
    files = sorted(p.relative_to(root).as_posix() for p in root.rglob("*.parquet"))
    key = records[0].key
    assert files[0].startswith("uplink_commits/day=") and files[0].endswith(f"/{key}.parquet")
    assert files[1:] == [f"{UPLINK_QUARANTINE}/{key}.parquet", f"uplink_summaries/{key}.parquet"]
    got = pq.read_table(root / files[2]).to_pylist()
    assert [(r["machine"], str(r["day"]), r["seq"]) for r in got] == [
        (m, "2026-01-01", seq) for m in ("wl-1", "wl-2") for seq in range(1, 6)
    ]
    assert all((root / f).resolve().is_relative_to(root.resolve()) for f in files)
    assert store.prepare(root, T0) == 0


def test_a_commit_cut_short_leaves_no_row_and_no_id(tmp_path, monkeypatch):
    root = ds.open_dataset(tmp_path / "ds", create=True)
    real, moved = store._move, []

    def crash_after_two(src, dest):
        if len(moved) == 2:
            raise KeyboardInterrupt  # as a kill between two renames
        moved.append(dest)
        real(src, dest)

    monkeypatch.setattr(store, "_move", crash_after_two)
    with pytest.raises(KeyboardInterrupt):
        store.commit_batch(root, a_batch(), store.key_of(1), T0)
    monkeypatch.undo()
    assert len(list(root.glob("uplink_*/*.parquet"))) == 2 and not store.record_paths(root)
    assert not list((root / ds.STAGING).glob("ingest-*"))  # its staging folder went with it
    assert store.prepare(root, T0) == 2
    seen, records = store.load_seen(root)
    assert not records and not seen.ranges and not list(root.rglob("*.parquet"))


def test_a_damaged_commit_record_is_named(tmp_path):
    root = ds.open_dataset(tmp_path / "ds", create=True)
    store.commit_batch(root, a_batch(2), store.key_of(1), T0)
    (rec,) = store.record_paths(root)
    rec.write_bytes(rec.read_bytes()[:-20])
    with pytest.raises(ds.Damaged, match=rec.name):
        store.load_seen(root)


# -- the command line --------------------------------------------------------------------------------


def cli_args(**over):
    from cmcan.cli.fleet_ingest import mqtt_section

    base = dict(
        broker="mqtt://127.0.0.1:1883",
        protocol="5",
        client_id="ingest",
        topic_prefix="cmcan",
        username=None,
        password_file=None,
        batch=100,
        ca_file=None,
        cert_file=None,
        key_file=None,
        no_verify_hostname=False,
    )
    return mqtt_section(SimpleNamespace(**{**base, **over}))


@pytest.mark.parametrize(
    ("over", "message", "kind"),
    [
        ({"broker": "http://x"}, "expected mqtt://HOST", Kind.USAGE),
        ({"broker": "mqtt://u:pw@x"}, "no user name or password in the URL", Kind.USAGE),
        ({"broker": "mqtt://x:99999"}, "port", Kind.USAGE),
        ({"password_file": "pw"}, "uplink.mqtt.password_file: needs mqtt.username", Kind.CONFIG),
        ({"ca_file": "ca.pem"}, "TLS is not enabled", Kind.CONFIG),
        ({"broker": "mqtts://x", "cert_file": "c.pem"}, "cert_file and key_file go together", Kind.CONFIG),
        ({"client_id": "a\x00b"}, "uplink.mqtt.client_id", Kind.CONFIG),
        ({"topic_prefix": "a/+"}, "uplink.mqtt.topic_prefix", Kind.CONFIG),
    ],
)
def test_broker_options_are_checked_by_the_uplinks_rules(over, message, kind):
    from cmcan.uplink.config import UplinkSettings

    with pytest.raises(CmcanError, match=None) as err:
        UplinkSettings.from_raw({"mqtt": cli_args(**over)}, state_dir=".", source="cmcan fleet ingest")
    assert message in str(err.value) and err.value.kind is kind


def test_mqtts_gives_tls_on_8883():
    from cmcan.uplink.config import UplinkSettings

    m = UplinkSettings.from_raw({"mqtt": cli_args(broker="mqtts://broker.site")}, state_dir=".").mqtt
    assert (m.host, m.port, m.tls.enabled, m.max_inflight, m.client_id) == ("broker.site", 8883, True, 100, "ingest")


# -- the systemd unit ---------------------------------------------------------------------------------


def test_the_ingest_unit_verifies_and_restarts_only_what_a_restart_can_cure():
    import shutil
    import sys

    from cmcan.cli.errors import EX_DATAERR, EX_IOERR, EX_SOFTWARE, EX_TEMPFAIL, EXIT_CODES

    if shutil.which("systemd-analyze") is None:
        pytest.fail("systemd-analyze is not installed (the CI installs the systemd package)")
    unit = (Path(__file__).resolve().parents[1] / "systemd" / "cmcan-fleet-ingest.service").read_text()
    keys: dict[str, list[str]] = {}
    for line in unit.splitlines():
        if "=" in line and not line.startswith("#"):
            k, v = line.split("=", 1)
            keys.setdefault(k, []).append(v)
    prevent = {int(x) for v in keys["RestartPreventExitStatus"] for x in v.split()}
    for code in set(EXIT_CODES.values()):  # a damaged commit record (65) needs a person, unlike the uplink's
        assert (code in prevent) == (code not in {EX_IOERR, EX_TEMPFAIL, EX_SOFTWARE}), code
    assert EX_DATAERR in prevent
    for key in ("Type=notify", "WatchdogSec=", "DynamicUser=yes", "CapabilityBoundingSet=\n", "RestrictNamespaces=yes"):
        assert key in unit, key
    beside = Path(sys.executable).with_name("cmcan")
    exe = shutil.which("cmcan") or (str(beside) if beside.exists() else None)
    assert exe, "the cmcan entry point must be installed"
    systemd_verify(unit.replace("/usr/local/bin/cmcan", exe), "cmcan-fleet-ingest.service")


def test_the_command_line_names_the_option_and_exits_by_kind(tmp_path, capsys):
    from cmcan.cli import main

    base = ["fleet", "ingest", "--out", str(tmp_path / "ds")]
    assert main([*base, "--broker", "mqtt://x", "--batch", "5000"]) == 78
    assert "--batch (uplink.mqtt.max_inflight): expected an integer in [1, 1000], got 5000" in capsys.readouterr().err
    assert main([*base, "--broker", "mqtts://x", "--ca-file", str(tmp_path / "none.pem")]) == 66
    assert "--ca-file (uplink.mqtt.tls.ca_file):" in capsys.readouterr().err
    assert main([*base, "--broker", "mqtt://u:secret@x"]) == 64
    assert "secret" not in capsys.readouterr().err
    assert not (tmp_path / "ds").exists()  # nothing made before the options are checked


# -- the loop's rules, with a stand-in client and clock -------------------------------------------------


class LoopClient(FakeClient):
    """Hands the messages queued in ``inbox`` to the ingest at its next ``loop``."""

    def __init__(self, root: Path, ing: ig.Ingest) -> None:
        super().__init__(root)
        self.ing = ing
        self.inbox: list[tuple[str, bytes]] = []
        self.mid = 0

    def loop(self, timeout: float) -> int:
        for tp, body in self.inbox:
            self.mid += 1
            self.ing._on_message(self, None, SimpleNamespace(topic=tp, payload=body, mid=self.mid, qos=1))
        self.inbox.clear()
        return 0

    def disconnect(self) -> None:
        pass


def looping(tmp_path: Path) -> tuple[ig.Ingest, LoopClient, list[float]]:
    now = [100.0]
    m = SimpleNamespace(max_inflight=5, topic_prefix="cmcan", reconnect_min_s=1.0, reconnect_max_s=2.0)
    root = ds.open_dataset(tmp_path / "ds", create=True)
    ing = ig.Ingest(root, m, Seen(), clock=lambda: now[0], batch_wait_s=10.0)  # type: ignore[arg-type]
    client = LoopClient(ing.root, ing)
    ing.client, ing.connected = client, True
    return ing, client, now


def test_a_batch_is_committed_when_full_or_when_nothing_more_arrives(tmp_path):
    ing, client, now = looping(tmp_path)
    client.inbox = [(topic(), payload(seq=i)) for i in range(1, 8)]  # more than a batch (5)
    ing.step()
    assert client.acked == [1, 2, 3, 4, 5, 6, 7] and ing.stats.batches == 1  # full: committed at once
    client.inbox = [(topic(), payload(seq=8))]
    ing.step()
    assert client.acked[-1] == 7  # one message, just arrived: it waits
    now[0] += ig.IDLE_FLUSH_S * 2  # (well before batch_wait_s)
    ing.step()
    assert client.acked[-1] == 8 and ing.stats.batches == 2  # nothing more came: committed


def test_a_lost_connection_commits_what_arrived_and_acknowledges_nothing(tmp_path):
    ing, client, _now = looping(tmp_path)
    client.inbox = [(topic(), payload(seq=i)) for i in range(1, 3)]
    ing.step()  # arrived, not yet due
    ing.lost = True
    ing.step()
    assert client.acked == [] and ing.client is None and ing.failures == 1  # the broker sends them again
    seen, records = store.load_seen(ing.root)
    assert len(records) == 1 and ("wl-1/7d58", 2) in seen  # and they are duplicates then
