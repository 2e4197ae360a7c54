"""jaxcal.evaluation."""
