"""jaxcal.data."""
