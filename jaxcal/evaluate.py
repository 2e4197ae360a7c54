"""``python -m jaxcal.evaluate``: forwards to :mod:`jaxcal.cli.evaluate`, where the
command line lives (this path is the documented command; nothing else belongs here)."""

from jaxcal.cli.evaluate import main

if __name__ == "__main__":
    raise SystemExit(main())
