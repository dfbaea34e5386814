"""cmcan's send schedule on a real SocketCAN bus (vcan0): periodic outputs and answers on time whether
the bus is silent, flooded or full of requests. Collected into ``cases`` (one VM for all)."""

from __future__ import annotations
