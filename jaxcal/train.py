"""``python -m jaxcal.train``: forwards to :mod:`jaxcal.cli.train`, where the
command line lives (this path is the documented command; nothing else belongs here)."""

from jaxcal.cli.train import main

if __name__ == "__main__":
    raise SystemExit(main())
