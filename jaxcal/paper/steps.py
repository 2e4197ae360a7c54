"""Resumable steps of a long experiment, and two kinds of work they wrap.

:class:`StepStore` runs named steps once: each writes ``<out>/steps/<name>.json``
atomically when it finishes (with its wall time, its estimate, its seed and config) and
is skipped — its JSON read back — when the experiment runs again. The work:

* :func:`ensure_dataset`: a data file from a generator preset, built in-process by the
  same function as ``python -m jaxcal.generate``
  (:func:`jaxcal.models.turbofan.data.builders. build_dataset`), or an existing file
  checked against that preset;
* :func:`save_params` / :func:`load_params`: trained network weights (the E2E
  baselines) as flax msgpack, so an evaluation step can run after a restart.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable
from pathlib import Path

import jax
from flax import serialization

from jaxcal.models.turbofan.data.builders import build_dataset
from jaxcal.models.turbofan.data.ncmapss_io import ncmapss_info
from jaxcal.progress import progress_bar
from jaxcal.runs.folder import read_json, write_atomic, write_json
from jaxcal.settings import config_to_dict


class StepStore:
    """Named, resumable steps under ``<out>/steps/`` (see the module docstring).

    Args:
        out: the experiment's output folder.
        log: printer for progress lines.
    """

    def __init__(self, out: str | os.PathLike, *, log: Callable[[str], None] = print):
        self.out = Path(out)
        self.log = log

    def path(self, name: str) -> Path:
        """The JSON file of step ``name``."""
        return self.out / "steps" / f"{name}.json"

    def done(self, name: str) -> bool:
        """True when step ``name`` has finished in an earlier run."""
        return self.path(name).is_file()

    def read(self, name: str) -> dict:
        """The stored result of a finished step (``FileNotFoundError`` otherwise)."""
        return read_json(self.path(name))

    def run(
        self, name: str, work: Callable[[], dict], *, estimate_s: float, config: dict
    ) -> dict:
        """Run ``work`` unless step ``name`` is done; store and return its result.

        Args:
            name: step name (file name under ``steps/``).
            work: returns a JSON-ready dict.
            estimate_s: expected duration on the reference machine (printed, stored).
            config: the settings the step runs with (printed with its seed, stored).

        Returns:
            The step's dict with ``step``, ``seconds``, ``estimate_s`` and ``config``.
        """
        if self.done(name):
            self.log(f"[skip] {name}: {self.path(name)} exists")
            return self.read(name)
        self.log(f"[step] {name} (estimate ~{format_seconds(estimate_s)}) {config}")
        tic = time.perf_counter()
        result = work()
        record = {
            "step": name,
            "seconds": time.perf_counter() - tic,
            "estimate_s": estimate_s,
            "config": config,
            **result,
        }
        write_json(self.path(name), record)
        self.log(f"[done] {name} in {format_seconds(record['seconds'])}")
        return record


def format_seconds(seconds: float) -> str:
    """``95`` -> ``"1.6 min"``; ``40`` -> ``"40 s"``; ``7300`` -> ``"2.03 h"``."""
    if seconds < 60:
        return f"{seconds:.0f} s"
    if seconds < 3600:
        return f"{seconds / 60:.1f} min"
    return f"{seconds / 3600:.2f} h"


def ensure_dataset(cfg, path: str | os.PathLike, *, progress: bool = True) -> dict:
    """The data file of generator config ``cfg`` at ``path``, built if missing.

    Args:
        cfg: a :class:`jaxcal.models.turbofan.data.dataset_configs.DatasetConfig`.
        path: the ``.h5`` file.
        progress: show a tqdm bar over generation blocks.

    Returns:
        ``{"path", "generated", "rows", "units"}``.

    Raises:
        ValueError: an existing file was generated with another config (the message
            names the differing fields; delete the file to regenerate it).
    """
    path = Path(path)
    wanted = config_to_dict(cfg)
    if path.is_file():
        stored = ncmapss_info(str(path))["attrs"].get("config")
        stored = json.loads(stored) if isinstance(stored, str) else stored
        stored = stored or {}
        # fields added to the generator after the file was written are not a change
        diffs = sorted(k for k in set(stored) & set(wanted) if stored[k] != wanted[k])
        if diffs:
            raise ValueError(
                f"{path} was generated with another config (fields {diffs}); delete "
                "it to regenerate, or point the experiment at another data folder"
            )
        info = ncmapss_info(str(path))
        return {
            "path": str(path),
            "generated": False,
            "fields_not_in_file": sorted(set(wanted) - set(stored)),
            "rows": {s: v["rows"] for s, v in info["splits"].items()},
            "units": {s: v["units"] for s, v in info["splits"].items()},
        }
    path.parent.mkdir(parents=True, exist_ok=True)
    with (
        jax.enable_x64(True),
        progress_bar(
            desc=f"generate {cfg.name}", unit="block", disable=not progress
        ) as bar,
    ):

        def on_block(done: int, total: int, rows: int) -> None:
            bar.total = total
            bar.update(done - bar.n)
            bar.set_postfix(rows=f"{rows:,}", refresh=False)

        summary = build_dataset(cfg, path, on_block=on_block)
    return {
        "path": str(path),
        "generated": True,
        "rows": summary.rows,
        "units": summary.units,
    }


def save_params(path: str | os.PathLike, params) -> Path:
    """Write a pytree of arrays as flax msgpack, atomically."""
    return write_atomic(path, serialization.to_bytes(jax.device_get(params)))


def load_params(path: str | os.PathLike, target):
    """Read :func:`save_params` output into the structure of ``target``."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"missing {path}")
    return serialization.from_bytes(target, path.read_bytes())
