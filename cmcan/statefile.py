"""The daemon's persisted state: one JSON file in the state directory, written atomically."""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path

from cmcan.monitor.totals import StateError, Totals

log = logging.getLogger("cmcan.state")
STATE_FILE = "state.json"


class StateStore:
    def __init__(self, directory: str | Path) -> None:
        self.dir = Path(directory)
        self.path = self.dir / STATE_FILE

    def check_writable(self) -> str | None:
        """None when the directory can hold the state, else why not."""
        if not self.dir.exists():
            return f"{self.dir}: state directory does not exist"
        if not self.dir.is_dir():
            return f"{self.dir}: not a directory"
        if not os.access(self.dir, os.W_OK | os.X_OK):
            return f"{self.dir}: state directory is not writable by this user"
        return None

    def load(self) -> Totals:
        """The saved totals; a missing file is a fresh start, a corrupt one is kept aside, not lost."""
        if not self.path.exists():
            return Totals()
        try:
            return Totals.from_dict(json.loads(self.path.read_text(encoding="utf-8")))
        except (OSError, ValueError, StateError) as exc:
            aside = self._aside()
            self.path.replace(aside)
            log.error("%s: unreadable state (%s); kept as %s, starting with fresh totals", self.path, exc, aside)
            return Totals()

    def _aside(self) -> Path:
        n = 1
        while (candidate := self.dir / f"{STATE_FILE}.corrupt-{n}").exists():
            n += 1
        return candidate

    def save(self, totals: Totals) -> None:
        """Write a temporary file, fsync it, rename it over the old one, fsync the directory: a crash
        or power cut leaves either the old or the new state, never a torn one."""
        tmp = self.dir / f".{STATE_FILE}.tmp"
        data = json.dumps(totals.to_dict(), indent=1).encode("utf-8")
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o640)
        try:
            os.write(fd, data)
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, self.path)
        dfd = os.open(self.dir, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)
