"""File formats at the edge: run CSVs and CAN logs."""
