"""cellcal: online calibration of industrial robot cells."""

__version__ = "0.1.0"
