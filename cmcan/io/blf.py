"""The framing of a Vector BLF file, checked before python-can's ``BLFReader`` reads it.

The reader stops quietly at the end of the data it finds: a file cut short (a copy that did not
finish, a logger that lost power) replays its first part as if that were the whole log. The file's
own structure says when data are missing: the header records the file's size when the writer
closed it, and every object (a container of frames, mostly) records its size. Walking the object
headers (seeking over their bodies, nothing decompressed) finds a file shorter than its header says,
an object that runs past the end of the file, and bytes that are not an object.
"""

from __future__ import annotations

import logging
import struct
from pathlib import Path

log = logging.getLogger("cmcan.io")

# As python-can's can.io.blf reads them: the file header, and the base header of every object.
FILE_HEADER = struct.Struct("<4sLBBBBBBBBQQLL8H8H")
OBJ_HEADER = struct.Struct("<4sHHLL")


class BlfFramingError(ValueError):
    """A BLF file is truncated or not a BLF file; ``str()`` says where."""


def check_blf(path: str | Path) -> None:
    """Raise :class:`BlfFramingError` unless the file's objects fill it exactly as its header says."""
    p = Path(path)
    size = p.stat().st_size
    with open(p, "rb") as f:
        head = f.read(FILE_HEADER.size)
        if len(head) < FILE_HEADER.size:
            raise BlfFramingError(f"{p}: {size} bytes, shorter than a BLF file header ({FILE_HEADER.size} bytes)")
        fields = FILE_HEADER.unpack(head)
        if fields[0] != b"LOGG":
            raise BlfFramingError(f"{p}: not a BLF file (it does not start with 'LOGG')")
        header_size, declared = int(fields[1]), int(fields[10])
        if not FILE_HEADER.size <= header_size <= size:
            raise BlfFramingError(f"{p}: header size {header_size} does not fit a file of {size} bytes")
        # A writer that closed the file wrote its size into the header; one that died left the header's own size.
        closed = declared > header_size
        if closed and size < declared:
            raise BlfFramingError(f"{p}: truncated: the header says {declared} bytes, the file has {size}")
        pos = header_size
        while pos < size:
            f.seek(pos)
            raw = f.read(OBJ_HEADER.size)
            if len(raw) < OBJ_HEADER.size:
                raise BlfFramingError(f"{p}: truncated: {len(raw)} bytes of an object header at byte {pos}")
            signature, _hsize, _version, obj_size, _type = OBJ_HEADER.unpack(raw)
            if signature != b"LOBJ" or obj_size < OBJ_HEADER.size:
                raise BlfFramingError(f"{p}: no BLF object at byte {pos} (corrupt data)")
            end = pos + obj_size
            if end > size:
                raise BlfFramingError(
                    f"{p}: truncated: the object at byte {pos} needs {obj_size} bytes, {size - pos} are left"
                )
            pos = end + obj_size % 4  # objects are padded as the reader skips them
    if not closed:
        log.warning("%s: the BLF header was never completed (the logger did not stop cleanly)", p)
