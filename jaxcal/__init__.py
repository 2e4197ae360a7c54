"""jaxcal: real-time calibration of physics-based models in JAX.

Layers (imports flow one way): ``physics`` -> ``data`` -> ``surrogate`` -> ``envs`` ->
``agents`` / ``baselines`` -> ``training`` -> ``evaluation`` -> CLI modules. Importing the
package has no side effects: float64 is switched on only by entry points
(:func:`jaxcal.precision.enable_x64`).
"""

__version__ = "0.1.0"
