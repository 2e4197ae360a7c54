"""jaxcal.physics."""
