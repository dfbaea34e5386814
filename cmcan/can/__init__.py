"""The CAN vocabulary: frames, bit layouts, message checksums, DBC files, units, and J1939's
identifiers, NAME, address claim, requests, DM1 and transport."""
