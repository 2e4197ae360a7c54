"""jaxcal.nets: shared supervised-network building blocks (MLP, regression trainer)."""
