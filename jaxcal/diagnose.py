"""``python -m jaxcal.diagnose``: forwards to :mod:`jaxcal.cli.diagnose`, where the
command line lives (this path is the documented command; nothing else belongs here)."""

from jaxcal.cli.diagnose import main

if __name__ == "__main__":
    raise SystemExit(main())
