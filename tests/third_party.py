"""Fetch the public test material of python-can and cantools from their source distributions.

``python -m tests.third_party [DEST]`` downloads the sdists of the python-can and cantools versions
installed here from the package index (``pip download --no-binary :all:``) and unpacks
python-can's ``test/data`` (LGPL-3.0) and cantools' ``tests/files/dbc`` (MIT), each with its
project's licence, into DEST (default ``tests/third_party``, not part of the repository). The tests
of ``tests/test_public_corpora.py`` read them from there (or from ``$CMCAN_THIRD_PARTY``) and skip,
saying so, where they are absent. CI runs this before the test suite.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tarfile
import tempfile
from importlib.metadata import version
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DEFAULT = ROOT / "tests" / "third_party"
# (distribution, the folder wanted inside the sdist, where it goes under DEST)
WANTED = (
    ("python-can", "test/data", "python-can/test/data"),
    ("cantools", "tests/files/dbc", "cantools/tests/files/dbc"),
)
LICENCES = ("LICENSE", "LICENSE.txt", "COPYING", "COPYING.LESSER")


def fetch(dest: Path) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        for dist, inner, target in WANTED:
            spec = f"{dist}=={version(dist)}"
            subprocess.run(
                [sys.executable, "-m", "pip", "download", "-q", "--no-deps", "--no-binary", ":all:", "-d", tmp, spec],
                check=True,
            )
            sdist = next(p for p in Path(tmp).iterdir() if p.name.lower().replace("_", "-").startswith(dist))
            _unpack(sdist, inner, dest / target, dest / dist)
            sdist.unlink()
            print(f"{spec}: {inner} -> {dest / target}")


def _unpack(sdist: Path, inner: str, to: Path, licence_dir: Path) -> None:
    with tarfile.open(sdist) as tar:
        top = tar.getnames()[0].split("/")[0]
        for m in tar.getmembers():
            rel = m.name[len(top) + 1 :]
            if m.isfile() and rel.startswith(inner + "/"):
                out = to / rel[len(inner) + 1 :]
            elif m.isfile() and rel in LICENCES:
                out = licence_dir / rel
            else:
                continue
            out.parent.mkdir(parents=True, exist_ok=True)
            src = tar.extractfile(m)
            assert src is not None
            out.write_bytes(src.read())


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dest", nargs="?", default=str(DEFAULT))
    fetch(Path(ap.parse_args().dest))
