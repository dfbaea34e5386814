"""The forkserver's preload for ``tests.vcan.warm``: python-can's MF4 support deferred as the command
line does it (``cmcan.cli.main`` defers it again: a no-op), then what the tier's commands import.
Imported only in the forkserver: in a pytest process the deferral would hide asammdf from later tests.
"""

from cmcan.io import mf4support

mf4support.defer()

import can  # noqa: E402,F401 - python-can's bus (its MF4 support off, as above)

import cmcan.assemble  # noqa: E402 - the configuration, the DBC (cantools), the model (onnxruntime)
import cmcan.cli  # noqa: E402
import cmcan.cli.baseline  # noqa: E402
import cmcan.cli.check  # noqa: E402
import cmcan.cli.run  # noqa: E402
import cmcan.daemon.loop  # noqa: E402
import cmcan.daemon.preflight  # noqa: E402
import cmcan.uplink.feed  # noqa: E402,F401
