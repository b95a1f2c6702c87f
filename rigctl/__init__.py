"""rigctl: rig controller for camera and robot calibration."""

try:  # written by setuptools-scm into a build or an editable install, from git
    from rigctl._version import version as __version__
except ImportError:  # a source tree never built or installed
    from importlib.metadata import PackageNotFoundError, version

    try:
        __version__ = version("rigctl")
    except PackageNotFoundError:
        __version__ = "0.0.0+unknown"
