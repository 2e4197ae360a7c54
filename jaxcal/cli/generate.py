"""Command line: generate one of the paper's data sets in the N-CMAPSS HDF5 layout.

Usage::

    python -m jaxcal.generate dataset=cmapss [out=data/cmapss.h5] [field=value ...]
    python -m jaxcal.generate dataset=agtf30 seed=1 sensor_snr_db=70

``dataset`` picks a preset of
:data:`jaxcal.models.turbofan.data.dataset_configs.DATASETS` (cmapss, agtf30, tiny);
every other ``key=value`` overrides a field of
:class:`~jaxcal.models.turbofan.data.dataset_configs.DatasetConfig` (``dataset.seed=1``
works too). ``out`` defaults to ``data/<dataset>.h5``. The file is written atomically,
with the resolved config as the JSON root attribute ``config``; the temporary file of a
run that was killed mid-way is removed by the next run writing the same ``out``. A bad
argument (with the valid keys), or an ``out`` that cannot be written (empty, a folder,
under a file, in a read-only folder), prints the error and exits with code 2 before any
work.
"""

from __future__ import annotations

import os
import sys
import time

from jaxcal.cache import enable_compilation_cache
from jaxcal.cli.args import parse_command_line
from jaxcal.models.turbofan.data.dataset_configs import DATASETS, DatasetConfig
from jaxcal.models.turbofan.data.generation import (
    dataset_preset,
    generate_dataset,
    summary_line,
)
from jaxcal.settings import check_output_path, parse_overrides

USAGE = (
    "usage: python -m jaxcal.generate dataset={"
    + ",".join(DATASETS)
    + "} [out=PATH] [field=value ...]"
)


def parse_args(argv: list[str]) -> tuple[DatasetConfig, str]:
    """The resolved config and output path of a command line.

    Args:
        argv: ``key=value`` tokens (without the program name).

    Returns:
        (config, output path).

    Raises:
        ValueError: missing or unknown dataset, malformed token, unknown field (the
            message lists the valid keys), a badly typed value or an output path that
            cannot be written.
    """
    special, fields = {}, []
    for token in argv:
        key, sep, value = token.partition("=")
        key = key.strip()
        if not sep or not key:
            raise ValueError(f"malformed argument {token!r}: expected key=value")
        if key in ("dataset", "out"):
            if key in special:
                raise ValueError(f"key {key!r} given twice")
            special[key] = value
        else:
            fields.append(token.removeprefix("dataset."))
    name = special.get("dataset")
    # the keys are checked first (against any preset when none is named): a misspelt
    # ``datset=`` is named as such, with the closest key, not as a missing dataset
    preset = next(iter(DATASETS.values())) if name is None else dataset_preset(name)
    try:
        cfg = parse_overrides(fields, preset)
    except ValueError as err:
        raise ValueError(f"{err} (and: dataset, out)") from None
    dataset_preset(name)  # no dataset= at all: say so
    out = special["out"] if "out" in special else os.path.join("data", f"{name}.h5")
    return cfg, check_output_path(out, "out")


def main(argv: list[str] | None = None) -> int:
    """Run the CLI; returns the process exit code (0 ok, 2 bad arguments)."""
    parsed, code = parse_command_line(argv, parse_args, __doc__, USAGE)
    if code is not None:
        return code
    cfg, out = parsed

    enable_compilation_cache()  # the engine's solve compiles in ~45 s; reruns reuse it
    print(f"generating {cfg.name!r} ({cfg.kind}, engine {cfg.engine}) -> {out}")
    start = time.perf_counter()
    summary = generate_dataset(cfg, out)
    print(summary_line(summary, out, start))
    return 0


if __name__ == "__main__":
    sys.exit(main())
