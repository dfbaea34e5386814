"""The monitor core: pure functions and a state machine over values with timestamps from frames."""
