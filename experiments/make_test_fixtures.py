"""Write the small real-data fixtures the tests use (committed under tests/fixtures/).

* ``fd002_early.txt``: the first 3 cycles of the first 60 training units of FD002 (six
  operating conditions, early life), NASA format.
* ``fd001_life.txt``: the whole lives of the first 4 training units of FD001 (HPC
  degradation signature), NASA format.

    python experiments/make_test_fixtures.py
"""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT.parent / "shared" / "data" / "cmapss"
OUT = ROOT / "tests" / "fixtures"


def _lines(path: Path) -> list[str]:
    if not path.is_file():
        raise FileNotFoundError(f"C-MAPSS file not found: {path}")
    return path.read_text().splitlines(keepends=True)


def main() -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    fd002 = _lines(SRC / "train_FD002.txt")
    keep = [ln for ln in fd002 if int(ln.split()[0]) <= 60 and int(ln.split()[1]) <= 3]
    (OUT / "fd002_early.txt").write_text("".join(keep))
    fd001 = _lines(SRC / "train_FD001.txt")
    keep = [ln for ln in fd001 if int(ln.split()[0]) <= 4]
    (OUT / "fd001_life.txt").write_text("".join(keep))
    print(f"wrote {OUT}/fd002_early.txt and fd001_life.txt")


if __name__ == "__main__":
    main()
