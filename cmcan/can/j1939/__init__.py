"""SAE J1939 encodings cmcan needs: identifiers and PGNs (J1939-21), DM1 (J1939-73), the broadcast
transport protocol (BAM, J1939-21). Pure functions over integers and bytes; no bus, no clock."""
