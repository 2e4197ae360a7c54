"""jaxcal.models.turbofan.data."""
