"""Test-only reference implementations and fixtures (exact Kalman filter, analytic
calibration problem, synthetic N-CMAPSS files)."""
