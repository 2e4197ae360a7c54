"""Calibration methods as peers under one ``Calibrator(init, step)`` interface, and
the front door :func:`calibrate`."""

from jaxcal.calibrators.front import METHODS, CalibrationResult, calibrate

__all__ = ["METHODS", "CalibrationResult", "calibrate"]
