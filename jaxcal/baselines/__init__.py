"""jaxcal.baselines."""
