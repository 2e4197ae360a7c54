"""jaxcal.training."""
