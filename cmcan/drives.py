"""Several drives on one gateway: each drive its own configuration (its model, state directory,
outputs, J1939 address and NAME), run as one instance of the templated unit ``cmcan@.service`` each.
What must not overlap between them is checked here, before any of them runs: two daemons sending the
same identifier on one bus, claiming the same J1939 address or NAME, or sharing a state directory."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from cmcan.errors import CmcanError, Kind

if TYPE_CHECKING:  # hints only: cmcan check's parser imports this module
    from cmcan.assemble import Assembled


def config_files(given: Sequence[str]) -> list[str]:
    """The configuration files named: a directory stands for the ``*.yaml`` files in it (sorted)."""
    out: list[str] = []
    for g in given:
        p = Path(g)
        if p.is_dir():
            found = sorted(str(f) for f in p.glob("*.yaml") if f.is_file())
            if not found:
                raise CmcanError(f"{g}: no drive configurations (*.yaml) in this directory", Kind.NO_INPUT)
            out += found
        else:
            out.append(g)
    return out


def _sends(a: Assembled) -> dict[tuple[str, bool, int], str]:
    """Every identifier the drive's daemon sends, on its channel, with the message it carries."""
    m, cfg = a.monitor, a.cfg
    out = {}
    for what, msg in (
        ("CM ratio", m.outputs.ratio),
        ("CM quantity", m.outputs.quantity),
        ("warning", m.outputs.warning),
    ):
        out[(m.outputs.channel or cfg.output_channel, msg.extended, msg.frame_id)] = what
    if m.dm1_producer is not None:
        out[(cfg.output_channel, True, m.dm1_producer.frame_id)] = "DM1"
    return out


def conflicts(drives: Sequence[Assembled]) -> list[str]:
    """What two of the drives would both do on one gateway (empty: nothing)."""
    problems: list[str] = []
    for i, a in enumerate(drives):
        for b in drives[i + 1 :]:
            pair = f"{a.cfg.source} and {b.cfg.source}"
            sa, sb = _sends(a), _sends(b)
            for key in sorted(set(sa) & set(sb)):
                ch, ext, fid = key
                problems.append(
                    f"{pair} both send identifier 0x{fid:0{8 if ext else 3}X} on {ch} ({sa[key]} / {sb[key]})"
                )
            ja, jb = a.cfg.j1939, b.cfg.j1939
            if ja.enabled and jb.enabled and a.cfg.output_channel == b.cfg.output_channel:
                if ja.source_address == jb.source_address:
                    problems.append(
                        f"{pair} both claim J1939 address 0x{ja.source_address:02X} on {a.cfg.output_channel}"
                    )
                if ja.name is not None and ja.name == jb.name:
                    problems.append(f"{pair} have the same J1939 NAME {ja.name.hex()}: give each its own")
            if a.cfg.state.directory == b.cfg.state.directory:
                problems.append(f"{pair} share the state directory {a.cfg.state.directory}: give each its own")
    return problems
