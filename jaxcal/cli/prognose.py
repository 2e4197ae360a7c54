"""CLI: the remaining useful life of every test unit, from its calibrated health.

    python -m jaxcal.prognose train=<run-to-failure file> test=<file> out=<dir> \\
        [model=SPEC | engine=cmapss] [theta=A,B] [outputs=A,B] [noise=NAME:STD,...]
        [method=ukf] [truth=RUL_FD001.txt] [boundary=NAME:VALUE,...] [coverage=0.9]
        [samples=1000] [seed=0]

Calibrates the units of ``train=`` (each run to failure) and of ``test=`` (each cut
short) with ``method=`` (any method of ``jaxcal.calibrate``; the UKF by default),
learns the fleet's degradation and failure boundaries from the training units and
predicts each test unit's RUL with a ``coverage`` interval
(:func:`jaxcal.prognosis.pipeline.prognose`). ``model=`` is any
:func:`jaxcal.models.load` spec; ``engine=`` is its old name and ``cmapss`` the
default, where ``theta`` and ``outputs`` default to the C-MAPSS HPC and fan pairs and
the physical sensors (:data:`jaxcal.models.turbofan.model.PROGNOSIS_THETA`,
``PROGNOSIS_OUTPUTS``).
``boundary=name:value,...`` declares failure limits (then only those decide);
without it the boundaries are learned from the training units' last cycles.
``truth=`` (one true RUL per line, in test-unit order: NASA's ``RUL_FD00x.txt``)
scores the prediction. Writes ``rul.csv`` (columns ``unit,rul,rul_low,rul_high``),
``report.json``, ``report.md`` and figures to ``out`` (:mod:`jaxcal.prognosis.report`).
Arguments are ``key=value`` (:func:`jaxcal.settings.parse_overrides`); a missing file,
an unknown key or a bad value exits with code 2 and a message naming the field.
float64 is enabled here, at the entry point. See ``docs/prognosis.md``.
"""

from __future__ import annotations

import dataclasses
import math
import os
import sys

from jaxcal.cli.args import parse_command_line
from jaxcal.settings import check_output_path, config_to_dict, parse_overrides

USAGE = (
    "usage: python -m jaxcal.prognose train=FILE test=FILE out=DIR "
    "[model=SPEC|engine=cmapss] [theta=A,B] [outputs=A,B] [noise=NAME:STD,...|STD] "
    "[method=ukf] [truth=FILE] [boundary=NAME:VALUE,...] [coverage=0.9] "
    "[samples=1000] [seed=0] [key=value ...]"
)
DATA_EXTENSIONS = (".csv", ".parquet", ".pq", ".h5", ".hdf5", ".txt")


@dataclasses.dataclass(frozen=True)
class PrognoseConfig:
    """Command-line settings of ``python -m jaxcal.prognose``."""

    train: str = ""  # run-to-failure units: .csv / .parquet / .h5 / C-MAPSS .txt
    test: str = ""  # units to predict, same formats (required)
    out: str = ""  # output folder (required)
    model: str = ""  # jaxcal.models.load spec ("" = engine=)
    engine: str = "cmapss"  # old name of model=
    theta: tuple[str, ...] = ()  # () = the turbofan's PROGNOSIS_THETA, else all
    outputs: tuple[str, ...] = ()  # () = the turbofan's PROGNOSIS_OUTPUTS, else all
    noise: str = ""  # measurement noise std: name:std,... or one number ("" = default)
    method: str = "ukf"  # calibration method (jaxcal.calibrate's)
    truth: str = ""  # true RULs, one per line in test-unit order (optional)
    boundary: tuple[str, ...] = ()  # declared failure limits, name:value
    coverage: float = 0.9  # nominal coverage of the RUL interval
    samples: int = 1000  # RUL samples per unit
    # a parameter's trend family in age: polyN or expL (None: chosen on held-out units)
    trend: str | None = None
    max_tightness: float = 0.35  # a learned boundary decides at most this tightness
    noise_scale: float | None = None  # None: learned on held-out training units
    folds: int = 5  # held-out folds of the noise-scale check
    seed: int = 0  # RUL sampling seed

    @property
    def model_spec(self) -> str:
        return self.model or self.engine


def parse_boundary(items) -> dict[str, float]:
    """``boundary=name:value,...`` as ``{name: value}``; a ValueError naming the field
    for an item without ``:``, a value that is not a finite number or a name given
    twice."""
    out: dict[str, float] = {}
    for item in items:
        name, sep, text = item.partition(":")
        name = name.strip()
        try:
            value = float(text) if sep and name else math.nan
        except ValueError:
            value = math.nan
        if not math.isfinite(value):
            raise ValueError(
                f"boundary={item!r}: expected name:value (a finite limit), e.g. "
                "boundary=HPC_eff_mod:-0.05,HPC_flow_mod:-0.04"
            )
        if name in out:
            raise ValueError(f"boundary: {name!r} is given twice")
        out[name] = value
    return out


def _check_file(path: str, field: str) -> None:
    if not path:
        raise ValueError(f"{field}=<file> is required")
    if not os.path.isfile(path):
        raise ValueError(f"{field}={path!r}: file not found")


def parse_args(argv: list[str]) -> PrognoseConfig:
    """The checked settings of a command line (nothing heavy imported).

    Raises:
        ValueError: naming the bad key or value and the expected form.
    """
    cfg = parse_overrides(argv, PrognoseConfig())
    for field in ("train", "test"):
        _check_file(getattr(cfg, field), field)
        if os.path.splitext(getattr(cfg, field))[1].lower() not in DATA_EXTENSIONS:
            raise ValueError(
                f"{field}={getattr(cfg, field)!r}: expected a .csv, .parquet, .h5 or "
                ".txt (C-MAPSS) file"
            )
    if cfg.truth:
        _check_file(cfg.truth, "truth")
    if not cfg.out:
        raise ValueError("out=<folder> is required (rul.csv, report.md, figures)")
    check_output_path(cfg.out, "out", folder=True)  # refused now, not after the work
    parse_boundary(cfg.boundary)
    if not 0.0 < cfg.coverage < 1.0:
        raise ValueError(f"coverage={cfg.coverage}: expected a share in (0, 1)")
    if cfg.trend is not None:  # imported here: --help and the other checks load no jax
        from jaxcal.prognosis.trends import check_trend

        check_trend(cfg.trend)
    for field, low in (("samples", 10), ("folds", 2)):
        if getattr(cfg, field) < low:
            raise ValueError(f"{field}={getattr(cfg, field)}: expected at least {low}")
    if cfg.max_tightness <= 0:
        raise ValueError(f"max_tightness={cfg.max_tightness}: expected > 0")
    if cfg.noise_scale is not None and not cfg.noise_scale > 0:
        raise ValueError(f"noise_scale={cfg.noise_scale}: expected > 0 (or none)")
    return cfg


def run(cfg: PrognoseConfig) -> dict:
    """Calibrate, predict and write the report of ``cfg``; returns the report dict."""
    # light --help: imported after the arguments are checked (jaxcal.cli.args)
    from jaxcal.cache import enable_compilation_cache
    from jaxcal.fleet.method import parse_noise
    from jaxcal.models import load
    from jaxcal.models.turbofan.model import (
        PROGNOSIS_OUTPUTS,
        PROGNOSIS_THETA,
        is_turbofan,
    )
    from jaxcal.precision import enable_x64
    from jaxcal.prognosis.pipeline import PrognosisConfig, prognose
    from jaxcal.prognosis.report import write_prognosis
    from jaxcal.prognosis.score import read_truth

    noise = parse_noise(cfg.noise)  # a bad value fails before the model loads
    # a bad truth file fails before the calibration; its count is checked after
    truth = read_truth(cfg.truth) if cfg.truth else None
    enable_x64()
    enable_compilation_cache()
    model = load(cfg.model_spec)
    theta, outputs = list(cfg.theta) or None, list(cfg.outputs) or None
    if is_turbofan(model):  # C-MAPSS's fault mode and physical sensors
        theta = theta or list(PROGNOSIS_THETA)
        outputs = outputs or list(PROGNOSIS_OUTPUTS)
    if theta is not None:
        model.parameter_index(theta)  # a bad name fails before the data is read
    config = PrognosisConfig(
        method=cfg.method, coverage=cfg.coverage, samples=cfg.samples,
        trend=cfg.trend, max_tightness=cfg.max_tightness,
        noise_scale=cfg.noise_scale, folds=cfg.folds, seed=cfg.seed,
    )  # fmt: skip
    result = prognose(
        model, cfg.train, cfg.test, theta=theta, noise=noise,
        boundary=parse_boundary(cfg.boundary) or None, config=config,
        outputs=outputs,
    )  # fmt: skip
    if truth is not None:
        truth = read_truth(cfg.truth, num_units=len(result.prediction.unit))
    source = {"train": cfg.train, "test": cfg.test, "truth": cfg.truth or None}
    settings = {
        **config_to_dict(cfg),
        "model_name": model.name,
        "theta": list(result.model.names),
        "outputs": outputs,
        "prognosis": config_to_dict(config),
    }
    return write_prognosis(cfg.out, result, truth=truth, source=source, config=settings)


def summary_line(rep: dict) -> str:
    """The console's one line: units, the score when there is a truth, the folder."""
    line = f"prognosis: {rep['test_units']} test units"
    if "score" in rep:
        s = rep["score"]
        line += (
            f", RMSE {s['rmse']:.2f} cycles, PHM08 score {s['phm08_score']:.1f}, "
            f"{rep['coverage']:.0%} interval coverage {s['coverage']:.3f}"
        )
    return line + f"; rul.csv and report.md in {rep['out']}"


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code (0 done, 2 bad arguments or data)."""
    cfg, code = parse_command_line(argv, parse_args, __doc__, USAGE)
    if code is not None:
        return code
    try:
        rep = run(cfg)
    except (ValueError, FileNotFoundError) as err:
        print(f"jaxcal.prognose: {err}", file=sys.stderr)
        return 2
    print(summary_line(rep))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
