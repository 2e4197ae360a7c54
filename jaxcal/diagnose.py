"""CLI: close the loop on a data file — residual, traced effect, error before and after.

    python -m jaxcal.diagnose data=<file.h5 | C-MAPSS .txt> engine=cmapss \\
        calibrate=HPT_eff_mod [out=<dir>] [units=1,2] [sensors=T24,T30] [max_rows=20000]

Writes ``report.md``, ``report.json`` and PNG figures to ``out`` (default
``results/diagnose/<file stem>/``). Arguments are ``key=value`` (``jaxcal.cli_args``);
an unknown key, a missing required one or bad data exits with code 2 and a message that
names the field and the valid choices. An N-CMAPSS file (1 Hz) is read with a row stride
chosen so that about ``max_rows`` rows are loaded (``stride`` overrides it), and only
its measured sensors X_s unless ``sensors`` names others; a C-MAPSS file has one row per
flight and is subsampled evenly within units down to ``max_rows`` (0 keeps every row).
Rows holding NaN or Inf are dropped, and the console, ``report.md`` and ``report.json``
say how many (per column); ``rename=T_24:T24`` maps N-CMAPSS column names.
"""

from __future__ import annotations

import dataclasses
import os
import sys
import time

from jaxcal.settings import check_output_path, config_to_dict, parse_overrides


@dataclasses.dataclass(frozen=True)
class DiagnoseConfig:
    """Command-line settings of ``python -m jaxcal.diagnose``."""

    data: str = ""  # N-CMAPSS .h5 file or NASA C-MAPSS .txt file (required)
    engine: str = "cmapss"  # engine configuration: cmapss or agtf30
    calibrate: tuple[str, ...] = ()  # declared health modifiers (required)
    out: str = ""  # output directory (default results/diagnose/<file stem>/)
    units: tuple[int, ...] = ()  # unit ids to use (default all)
    sensors: tuple[str, ...] = ()  # sensors of the residual (default all usable)
    max_rows: int = 20000  # subsample to about this many rows (0: all)
    split: str = "dev"  # N-CMAPSS split: dev or test
    stride: int = 0  # N-CMAPSS load stride (0: from max_rows)
    knots: int = 6  # B-spline functions per unit and declared modifier
    families: tuple[str, ...] = ()  # effect families (default all)
    bic_margin: float = 10.0  # delta BIC for "found" and for confounding
    alpha: float = 0.01  # family-wise level of the likelihood-ratio tests
    # N-CMAPSS column names to map, <file name>:<jaxcal name> (e.g. T_24:T24)
    rename: tuple[str, ...] = ()


def load_record(cfg: DiagnoseConfig):
    """Read the data file of ``cfg`` (C-MAPSS text or N-CMAPSS HDF5).

    Rows with NaN / Inf values are dropped (``Record.dropped`` counts them per column;
    the console, report.md and report.json say so), never passed on in silence.
    """
    from jaxcal.data.cmapss_text import load_cmapss_text
    from jaxcal.data.ncmapss_io import load_ncmapss, ncmapss_info, parse_rename
    from jaxcal.physics.constants import MEASURED_SENSOR_NAMES

    if not os.path.isfile(cfg.data):
        raise ValueError(f"data={cfg.data!r}: file not found")
    units = list(cfg.units) or None
    if cfg.data.endswith((".h5", ".hdf5")):
        rename = parse_rename(cfg.rename)
        stride = cfg.stride
        if stride <= 0:
            info = ncmapss_info(cfg.data, rename=rename)
            rows = info["splits"].get(cfg.split, {}).get("rows", 0)
            stride = max(1, rows // cfg.max_rows) if cfg.max_rows else 1
        # the virtual sensors X_v are not measured on an engine: X_s unless asked
        sensors = list(cfg.sensors) or list(MEASURED_SENSOR_NAMES)
        return load_ncmapss(
            cfg.data,
            split=cfg.split,
            units=units,
            sensors=sensors,
            stride=stride,
            rename=rename,
            nonfinite="drop",
        )
    if cfg.data.endswith(".txt"):
        record = load_cmapss_text(cfg.data, nonfinite="drop")
        return record if units is None else record.select_units(units)
    raise ValueError(
        f"data={cfg.data!r}: expected a .h5 (N-CMAPSS) or .txt (C-MAPSS) file"
    )


def output_dir(cfg: DiagnoseConfig) -> str:
    """The report folder: ``out``, or ``results/diagnose/<file stem>/``."""
    if cfg.out:
        return cfg.out
    name = os.path.splitext(os.path.basename(cfg.data))[0]
    return os.path.join("results", "diagnose", name)


def run(cfg: DiagnoseConfig) -> dict:
    """Diagnose ``cfg.data`` and write the report; returns the report dict."""
    from jaxcal.diagnosis.discrepancy import DiscrepancyConfig
    from jaxcal.diagnosis.identify import IdentifyConfig
    from jaxcal.diagnosis.pipeline import LoopConfig, diagnose_record
    from jaxcal.diagnosis.report import dropped_rows_line, write_report
    from jaxcal.physics import load_engine
    from jaxcal.precision import enable_compilation_cache, enable_x64

    if not cfg.data:
        raise ValueError("data=<file.h5 | C-MAPSS .txt> is required")
    if not cfg.calibrate:
        raise ValueError("calibrate=<comma-separated health modifiers> is required")
    out = check_output_path(output_dir(cfg), "out", folder=True)  # before the work
    enable_x64()
    enable_compilation_cache()
    engine = load_engine(cfg.engine)
    record = load_record(cfg)
    loop_cfg = LoopConfig(
        knots=cfg.knots,
        families=cfg.families,
        identify=IdentifyConfig(alpha=cfg.alpha, bic_margin=cfg.bic_margin),
        discrepancy=DiscrepancyConfig(margin=cfg.bic_margin),
    )
    start = time.time()
    res = diagnose_record(
        record,
        engine,
        cfg.calibrate,
        loop_cfg,
        sensors=list(cfg.sensors) or None,
        max_rows=cfg.max_rows or None,
    )
    config = {
        **config_to_dict(cfg),
        "loop": config_to_dict(loop_cfg),
        "seconds": time.time() - start,
    }
    rep = write_report(out, res, source=cfg.data, engine=cfg.engine, config=config)
    rep["out"] = out
    dropped = rep["data"]["dropped"]
    if dropped["rows"]:  # said here, in report.md and in report.json
        print(f"jaxcal.diagnose: {cfg.data}: {dropped_rows_line(dropped)}")
    return rep


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code (0 done, 2 bad arguments or data)."""
    argv = sys.argv[1:] if argv is None else argv
    try:
        cfg = parse_overrides(argv, DiagnoseConfig())
        rep = run(cfg)
    except (ValueError, FileNotFoundError) as err:
        print(f"jaxcal.diagnose: {err}", file=sys.stderr)
        return 2
    found = (
        ", ".join(
            f"{e['name']} = {e['size']:.4g} ± {e['std']:.2g} {e['unit']}"
            for e in rep["identified"]
        )
        or "no library effect"
    )
    b, a = rep["before"], rep["after"]
    print(
        f"verdict: {rep['verdict']} ({found}); mean tracking RMSE "
        f"{b['mean_tracking_rmse_norm']:.3f} -> {a['mean_tracking_rmse_norm']:.3f} "
        f"noise std; report in {rep['out']}/report.md"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
