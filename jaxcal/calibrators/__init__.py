"""Calibration methods as peers under one ``Calibrator(init, step)`` interface, and
the front door :func:`calibrate`.

Folders by job:

* :mod:`.front`: the front door (:func:`calibrate`): the call read, the data
  screened (noise, outliers), per-row results, units carrying some parameters only;
* :mod:`.methods`: the method registry, one package a method (``ukf``, ``ls``,
  ``e2e``, ``policy``, ``ekf``), each its implementation beside its ``METHOD``;
* :mod:`.programs`: their compiled programs, once per process and kept on disk;
* :mod:`.uncertainty`: honest stds (conformal bands, the checks of a reported std);
* here: the interface and its guarded runners (:mod:`.interface`, :mod:`.guard`),
  the Gaussian filters' shared skeleton and steps (:mod:`.gaussian_filter`,
  :mod:`.ukf`, :mod:`.ukf_steps`).
"""

from jaxcal.calibrators.front.door import METHODS, calibrate
from jaxcal.calibrators.front.result import CalibrationResult

__all__ = ["METHODS", "CalibrationResult", "calibrate"]
