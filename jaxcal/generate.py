"""``python -m jaxcal.generate``: forwards to :mod:`jaxcal.cli.generate`, where the
command line lives (this path is the documented command; nothing else belongs here)."""

from jaxcal.cli.generate import main

if __name__ == "__main__":
    raise SystemExit(main())
