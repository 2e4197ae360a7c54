"""``python -m jaxcal.validate``: the documented command of the engine's checks; its
``__main__`` forwards to :mod:`jaxcal.cli.validate`, where the command line lives."""
