"""Calibration methods as peers under one ``Calibrator(init, step)`` interface, and
the front door :func:`calibrate`."""

from jaxcal.calibrators.front import METHODS, calibrate
from jaxcal.calibrators.result import CalibrationResult

__all__ = ["METHODS", "CalibrationResult", "calibrate"]
