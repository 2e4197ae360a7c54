"""CLI: close the loop on a data file — residual, traced effect, error before and after.

    python -m jaxcal.diagnose model=<name | module:attr | path.py:attr> \\
        data=<file .csv | .parquet | .h5 | .txt> calibrate=<declared parameters> \\
        [out=<dir>] [units=1,2] [outputs=T24,T30] [max_rows=20000]

Any :class:`jaxcal.Model`, static or with hidden states (``jaxcal.models.load``
spec; a model with memory is diagnosed in output-error form); ``engine=`` is the
old name of ``model=`` and ``cmapss`` the default, so turbofan commands of before
still work. Writes ``report.md``, ``report.json`` and PNG figures to ``out`` (default
``results/diagnose/<file stem>/``), naming effects in the model's vocabulary and units,
per unit (report.json ``identified[i].units``: ``unit``, ``carries``, ``size``,
``size_std``, ``onset``; ``units.png``) and with the plausibility flags of the verdict
(``flags``; :mod:`jaxcal.diagnosis.report.plausibility`), which the console line
repeats, and, when effects were added, the extended model ``extended_model.json`` that
``model=`` accepts on every command line (the loop closed: the twin tracks the effect
in real time with any method).
Arguments are ``key=value`` (``jaxcal.settings.parse_overrides``); an unknown key, a
missing required one or bad data exits with code 2 and a message that names the field
and the valid choices. CSV / Parquet columns are named as the model's conditions and
outputs, with optional ``unit``, ``time`` (the cycle) and true-parameter columns
(:func:`jaxcal.data.readers.read_dataset`). An N-CMAPSS file (1 Hz) is read with a row
stride chosen so that about ``max_rows`` rows are loaded (``stride`` overrides it), and
only its measured sensors X_s unless ``outputs`` names others; a C-MAPSS file has one
row per flight. Every data set is subsampled evenly within units down to ``max_rows``
(0 keeps every row; a note on the console and in the report says how many were
used). Rows holding NaN or Inf are dropped, and the console, ``report.md`` and
``report.json`` say how many (per column); ``rename=T_24:T24`` maps column names,
``ignore=a,b`` leaves table columns out. float64 is enabled here, at
the entry point.

On several processes (``jax.distributed``: the same command on each, with its own
``--process-id``; or the ``JAXCAL_COORDINATOR`` / ``JAXCAL_NUM_PROCESSES`` /
``JAXCAL_PROCESS_ID`` variables, as ``python -m jaxcal.fleet``), every process reads
the data and runs the same diagnosis; the model's evaluations are split by units and
gathered (:mod:`jaxcal.diagnosis.data.sharding`), so each process reaches the verdict of
one process. Process 0 alone writes the report and prints the verdict line::

    python -m jaxcal.diagnose data=fleet.csv calibrate=wear model=pump.py:PUMP \\
        --coordinator 10.0.0.1:12355 --num-processes 2 --process-id 0
"""

from __future__ import annotations

import dataclasses
import os
import sys
import time

from jaxcal.cli.args import CLUSTER_USAGE, parse_command_line, split_cluster_args
from jaxcal.settings import check_output_path, config_to_dict, parse_overrides

USAGE = (
    "usage: python -m jaxcal.diagnose data=FILE calibrate=A,B [model=SPEC] [out=DIR] "
    "[units=1,2] [outputs=A,B] [max_rows=N] [kinds=K,...] [rename=FILE:MODEL,...] "
    f"[ignore=A,B] [key=value ...] {CLUSTER_USAGE}"
)


@dataclasses.dataclass(frozen=True)
class DiagnoseConfig:
    """Command-line settings of ``python -m jaxcal.diagnose``."""

    data: str = ""  # .csv / .parquet / N-CMAPSS .h5 / C-MAPSS .txt file (required)
    model: str = ""  # model spec: name, module:attr or path.py:attr (default engine)
    engine: str = "cmapss"  # old name of model= (a registered turbofan)
    calibrate: tuple[str, ...] = ()  # declared parameters (required)
    out: str = ""  # output directory (default results/diagnose/<file stem>/)
    units: tuple[int, ...] = ()  # unit ids to use (default all)
    outputs: tuple[str, ...] = ()  # outputs of the residual (default all usable)
    sensors: tuple[str, ...] = ()  # old name of outputs=
    max_rows: int = 20000  # subsample to about this many rows (0: all)
    split: str = "dev"  # N-CMAPSS split: dev or test
    stride: int = 0  # N-CMAPSS load stride (0: from max_rows)
    knots: int = 6  # B-spline functions per unit and declared parameter
    kinds: tuple[
        str, ...
    ] = ()  # effect kinds (default all; jaxcal.diagnosis.kinds.table)
    families: tuple[str, ...] = ()  # old name of kinds=
    bic_margin: float = 10.0  # delta BIC for "found" and for confounding
    alpha: float = 0.01  # family-wise level of the likelihood-ratio tests
    # column names to map, <file name>:<model name> (e.g. T_24:T24)
    rename: tuple[str, ...] = ()
    # table columns to leave out (e.g. a truth column the model does not know)
    ignore: tuple[str, ...] = ()

    @property
    def model_spec(self) -> str:
        return self.model or self.engine

    @property
    def residual_outputs(self) -> list[str] | None:
        return list(self.outputs or self.sensors) or None


def parse_args(argv: list[str]) -> tuple[DiagnoseConfig, dict]:
    """The config and the cluster settings of a command line (``cluster``: the
    keyword arguments of :func:`jaxcal.fleet.distributed.initialize`).

    Raises:
        ValueError: naming the bad key or flag and the expected form.
    """
    rest, flags = split_cluster_args(argv)
    return parse_overrides(rest, DiagnoseConfig()), flags.resolve()


def _rename(cfg: DiagnoseConfig) -> dict:
    # light --help: imported after the arguments are checked (jaxcal.cli.args)
    from jaxcal.data.table_checks import parse_rename

    return parse_rename(cfg.rename)


def load_data(cfg: DiagnoseConfig, model):
    """Read the data file of ``cfg`` for ``model`` as a
    :class:`~jaxcal.data.dataset.Dataset` (one split of an N-CMAPSS file, a C-MAPSS
    text file or a table). Rows with NaN / Inf values are dropped and counted (the
    turbofan readers count the rows, ``Dataset.dropped_rows``), never passed on in
    silence.
    """
    # light --help: imported after the arguments are checked (jaxcal.cli.args)
    from jaxcal.data.readers import read_dataset
    from jaxcal.models.turbofan.data.datasets import read_file, read_ncmapss_split

    if not os.path.isfile(cfg.data):
        raise ValueError(f"data={cfg.data!r}: file not found")
    ext = os.path.splitext(cfg.data)[1].lower()
    units = list(cfg.units) or None
    if ext in (".h5", ".hdf5"):
        # light --help: imported after the arguments are checked (jaxcal.cli.args)
        from jaxcal.models.turbofan.data.ncmapss_io import ncmapss_info
        from jaxcal.models.turbofan.physics.constants import MEASURED_SENSOR_NAMES

        rename = _rename(cfg)
        stride = cfg.stride
        if stride <= 0:
            info = ncmapss_info(cfg.data, rename=rename)
            rows = info["splits"].get(cfg.split, {}).get("rows", 0)
            stride = max(1, rows // cfg.max_rows) if cfg.max_rows else 1
        # the virtual sensors X_v are not measured on an engine: X_s unless asked
        sensors = cfg.residual_outputs or list(MEASURED_SENSOR_NAMES)
        return read_ncmapss_split(
            cfg.data, cfg.split, label=False, units=units, sensors=sensors,
            stride=stride, rename=rename, nonfinite="drop",
        )  # fmt: skip
    if ext == ".txt":
        data = read_file(cfg.data, nonfinite="drop", rename=None)  # C-MAPSS text
        return data if units is None else data.select_units(units)
    if ext in (".csv", ".parquet", ".pq"):
        data = read_dataset(
            cfg.data, model, rename=_rename(cfg), ignore=cfg.ignore, nonfinite="drop"
        )
        return data if units is None else data.select_units(units)
    raise ValueError(
        f"data={cfg.data!r}: expected a .csv, .parquet, .h5 (N-CMAPSS) or .txt "
        "(C-MAPSS) file"
    )


def output_dir(cfg: DiagnoseConfig) -> str:
    """The report folder: ``out``, or ``results/diagnose/<file stem>/``."""
    if cfg.out:
        return cfg.out
    name = os.path.splitext(os.path.basename(cfg.data))[0]
    return os.path.join("results", "diagnose", name)


def run(cfg: DiagnoseConfig) -> dict:
    """Diagnose ``cfg.data`` and write the report (process 0 of a cluster); returns
    the report dict."""
    # light --help: imported after the arguments are checked (jaxcal.cli.args)
    import jax

    from jaxcal.cache import enable_compilation_cache, map_large_arrays
    from jaxcal.diagnosis.fitting.discrepancy import DiscrepancyConfig
    from jaxcal.diagnosis.fitting.identify import IdentifyConfig
    from jaxcal.diagnosis.pipeline import LoopConfig, diagnose
    from jaxcal.diagnosis.report.markdown import dropped_rows_line
    from jaxcal.diagnosis.report.write import report_dict, write_report
    from jaxcal.models import load
    from jaxcal.precision import enable_x64

    if not cfg.data:
        raise ValueError("data=<file .csv | .parquet | .h5 | .txt> is required")
    if not cfg.calibrate:
        raise ValueError("calibrate=<comma-separated declared parameters> is required")
    out = check_output_path(output_dir(cfg), "out", folder=True)  # before the work
    enable_x64()
    enable_compilation_cache()
    map_large_arrays()  # a fleet's arrays given back as they are freed (the peak)
    model = load(cfg.model_spec)
    model.parameter_index(cfg.calibrate)  # a bad name fails before the data is read
    data = load_data(cfg, model)
    loop_cfg = LoopConfig(
        knots=cfg.knots,
        kinds=cfg.kinds or cfg.families,
        identify=IdentifyConfig(alpha=cfg.alpha, bic_margin=cfg.bic_margin),
        discrepancy=DiscrepancyConfig(margin=cfg.bic_margin),
    )
    writer = jax.process_index() == 0  # on a cluster, process 0 alone writes
    start = time.time()
    res = diagnose(
        data,
        model,
        cfg.calibrate,
        loop_cfg,
        sensors=cfg.residual_outputs,
        max_rows=cfg.max_rows or None,
        progress=writer,
    )
    config = {
        **config_to_dict(cfg),
        "loop": config_to_dict(loop_cfg),
        "seconds": time.time() - start,
    }
    if not writer:
        rep = report_dict(res, source=cfg.data, model=model.name, config=config)
        return {**rep, "out": out}
    rep = write_report(
        out, res, source=cfg.data, model=model.name, config=config,
        base_spec=cfg.model_spec,
    )  # fmt: skip
    rep["out"] = out
    dropped = rep["data"]["dropped"]
    if dropped["rows"] or dropped["columns"]:  # said here, in report.md and .json
        print(f"jaxcal.diagnose: {cfg.data}: {dropped_rows_line(dropped)}")
    for note in rep["data"]["notes"]:  # wild readings and missing outputs, too
        if "outlier" in note or "outputs missing" in note:
            print(f"jaxcal.diagnose: {cfg.data}: {note}")
    return rep


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code (0 done, 2 bad arguments or data)."""
    parsed, code = parse_command_line(argv, parse_args, __doc__, USAGE)
    if code is not None:
        return code
    cfg, cluster = parsed
    # light --help: imported after the arguments are checked (jaxcal.cli.args)
    from jaxcal.fleet.distributed import initialize

    try:  # before any JAX computation
        initialize(**cluster)
    except RuntimeError as err:
        print(f"jaxcal.diagnose: {err}", file=sys.stderr)
        return 1
    try:
        rep = run(cfg)
    except (ValueError, FileNotFoundError) as err:
        print(f"jaxcal.diagnose: {err}", file=sys.stderr)
        return 2
    # light --help: imported after the arguments are checked (jaxcal.cli.args)
    import jax

    if jax.process_index() != 0:  # the writer's test of run(): process 0 reports
        return 0
    # light --help: imported after the arguments are checked (jaxcal.cli.args)
    from jaxcal.diagnosis.report.markdown import effect_line

    units = rep["data"]["units"]
    found = (
        ", ".join(effect_line(e, units) for e in rep["identified"])
        or "no library effect"
    )
    flags = sorted({f"{f['flag']} ({f['subject']})" for f in rep["flags"]})
    flagged = f"; FLAGGED: {'; '.join(flags)}" if flags else ""
    b, a = rep["before"], rep["after"]
    print(
        f"verdict: {rep['verdict']} ({found}){flagged}; mean tracking RMSE "
        f"{b['mean_tracking_rmse_norm']:.3f} -> {a['mean_tracking_rmse_norm']:.3f} "
        f"noise std; report in {rep['out']}/report.md"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
