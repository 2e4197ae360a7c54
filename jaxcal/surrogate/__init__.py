"""jaxcal.surrogate."""
