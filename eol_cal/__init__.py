"""eol-cal: end-of-line torque-ripple calibration for EPS PMSMs with a low-resolution encoder.

The library never touches the command line; ``cli/`` is a thin shell over it.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("eol-cal")
except PackageNotFoundError:  # running from a source tree without an install
    __version__ = "0.0.0+src"

from eol_cal.python_can import install as _install_can_finder

# python-can without its MF4 logger, whichever module imports it first (eol_cal.python_can)
_install_can_finder()
