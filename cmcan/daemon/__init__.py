"""The daemon: its receive loop of named steps (``loop``), what only ``run`` and ``check`` prepare
(``preflight``: the channel, the state directory), and the bus probe of ``check --channel-check``."""
