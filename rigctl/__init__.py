"""rigctl: rig controller for camera and robot calibration."""

__version__ = "0.1.0"
