"""``python -m jaxcal.validate``: forwards to :mod:`jaxcal.cli.validate`, where
the command line lives (this path is the documented command; nothing else belongs
here)."""

from jaxcal.cli.validate import main

if __name__ == "__main__":
    raise SystemExit(main())
