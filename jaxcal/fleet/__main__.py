"""``python -m jaxcal.fleet``: forwards to :mod:`jaxcal.cli.fleet`, where the command
line lives (this path is the documented command; nothing else belongs here)."""

from jaxcal.cli.fleet import main

if __name__ == "__main__":
    raise SystemExit(main())
