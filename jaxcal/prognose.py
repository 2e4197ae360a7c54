"""``python -m jaxcal.prognose``: forwards to :mod:`jaxcal.cli.prognose`, where the
command line lives (this path is the documented command; nothing else belongs here)."""

from jaxcal.cli.prognose import main

if __name__ == "__main__":
    raise SystemExit(main())
