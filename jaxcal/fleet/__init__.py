"""Fleet-scale calibration: sharded over devices, streamed in chunks, multi-process.

* :mod:`~jaxcal.fleet.sharded` — a 1-D ``Mesh`` over devices (axis ``"units"``) and
  :func:`run_sharded` / :func:`calibrate_sharded`: ``run_fleet`` under ``shard_map``,
  identical results to the single-device path.
* :mod:`~jaxcal.fleet.streaming` — :func:`calibrate_stream` over chunks of units with
  one compiled program and an incremental, atomic HDF5 output
  (:mod:`~jaxcal.fleet.results`); :mod:`jaxcal.models.turbofan.fleet` reads the chunks
  from an N-CMAPSS file.
* :mod:`~jaxcal.fleet.distributed` — ``jax.distributed`` set-up and
  :func:`calibrate_distributed` for units split over processes.
* ``python -m jaxcal.fleet`` — the command line (:mod:`jaxcal.cli.fleet`; see
  ``docs/fleet.md``): any model (``model=``) on an N-CMAPSS file or a table (``data=``,
  :mod:`~jaxcal.fleet.sources`), the method built from the front door's method table
  (:mod:`~jaxcal.fleet.method`); a parameter some units carry (an extended model's
  carriers) held at nominal in the others (:mod:`~jaxcal.fleet.per_unit`).

Any :class:`~jaxcal.calibrators.interface.Calibrator` works: UKF, least squares, a
deployed policy. Importing this package does not initialise JAX's backends, so
:func:`~jaxcal.fleet.distributed.initialize` can still run afterwards.
"""

from jaxcal.fleet.distributed import calibrate_distributed, initialize, process_share
from jaxcal.fleet.results import FleetResultWriter, read_results
from jaxcal.fleet.sharded import (
    calibrate_sharded,
    finish_units,
    make_unit_mesh,
    pad_units,
    run_sharded,
    shard_units,
    start_units,
)
from jaxcal.fleet.streaming import (
    UnitChunk,
    calibrate_stream,
    iter_array_chunks,
    plan_chunks,
    units_per_chunk,
)

__all__ = [
    "FleetResultWriter",
    "UnitChunk",
    "calibrate_distributed",
    "calibrate_sharded",
    "calibrate_stream",
    "finish_units",
    "initialize",
    "iter_array_chunks",
    "make_unit_mesh",
    "pad_units",
    "plan_chunks",
    "process_share",
    "read_results",
    "run_sharded",
    "shard_units",
    "start_units",
    "units_per_chunk",
]
