"""jaxcal.agents."""
