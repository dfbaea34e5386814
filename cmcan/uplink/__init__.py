"""Telematics uplink: CM results off the machine over MQTT, through a durable outbox.

The daemon (no network) writes what should leave the machine into a SQLite outbox in its state
directory (``outbox``, ``feed``); ``cmcan uplink`` (no bus) publishes from it with QoS 1 and deletes an
entry only after the broker's PUBACK (``publisher``). ``records`` turns monitor ticks and warning
transitions into entries and is pure; ``config`` is the ``uplink:`` configuration section;
``setup`` checks TLS files, password and outbox before the uplink starts.
"""
