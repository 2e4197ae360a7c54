"""jaxcal.envs."""
