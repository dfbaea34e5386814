"""cmcan's J1939 connection mode and trusted clears on a real SocketCAN bus (vcan0), with the kernel's
J1939 stack as the requester. Collected into ``cases`` (one VM for all)."""

from __future__ import annotations
