"""``python -m jaxcal.bench``: forwards to :mod:`jaxcal.cli.bench`, where the
command line lives (this path is the documented command; nothing else belongs here)."""

from jaxcal.cli.bench import main

if __name__ == "__main__":
    raise SystemExit(main())
