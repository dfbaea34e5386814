"""What cmcan's long-running services stand on: the state file, systemd's notify socket and
rate-limited logs (the daemon and the uplink alike)."""
