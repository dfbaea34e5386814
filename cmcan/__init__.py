"""cmcan: condition monitoring of hydrostatic drives on CAN with a gray-box model."""

__version__ = "0.1.0"
