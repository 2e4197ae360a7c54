"""Orbax checkpoints of whole pytrees, plus the resolved ``config.json`` beside them.

A host-only leaf (STYLE §2.7): training code hands a pytree (runner state, agent
params, optimiser states, key data, counters) to :class:`Checkpointer`, which wraps
``orbax.checkpoint.CheckpointManager`` with ``StandardSave`` / ``StandardRestore``.
Saves are asynchronous unless ``wait=True``; call
:meth:`Checkpointer.wait_until_finished` (or :meth:`Checkpointer.close`) before the
process exits.

Restores go into an abstract target (``jax.eval_shape(init_fn, jax.random.key(0))``).
The stored tree structure and leaf shapes are compared with the target *before* Orbax
reads any array, so a mismatch is one ``ValueError`` listing the missing, unexpected and
reshaped leaves (Orbax itself would fail deep inside TensorStore). Leaf dtypes follow
the target (Orbax casts), which lets a float32 run be restored under float64 and back.

Typed PRNG keys: orbax-checkpoint 0.12 happens to restore them directly, but that relies
on its handling of extended dtypes. We follow the style guide instead: every typed key
leaf is saved as ``jax.random.key_data(key)`` (a ``uint32`` array) and re-wrapped on
restore with ``jax.random.wrap_key_data`` using the PRNG implementation of the matching
target leaf. Checkpoints therefore hold only plain arrays and stay readable by any tool.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import jax
import orbax.checkpoint as ocp

from jaxcal.runs.atomic import write_atomic
from jaxcal.runs.metrics_log import to_json_value
from jaxcal.settings import config_from_dict, config_to_dict

CONFIG_FILE = "config.json"


def _is_typed_key(leaf: Any) -> bool:
    dtype = getattr(leaf, "dtype", None)
    return dtype is not None and jax.dtypes.issubdtype(dtype, jax.dtypes.prng_key)


def _key_impl(abstract_key: jax.ShapeDtypeStruct) -> Any:
    """PRNG implementation of an abstract typed key (read off a traced stand-in)."""
    found = []

    def probe(key):
        found.append(jax.random.key_impl(key))
        return jax.random.key_data(key)

    jax.eval_shape(probe, abstract_key)
    return found[0]


def _path_str(path: tuple) -> str:
    """'a/0/count' for a key path; Orbax metadata and live pytrees spell it alike."""
    parts = []
    for entry in path:
        for attr in ("key", "idx", "name"):
            if hasattr(entry, attr):
                parts.append(str(getattr(entry, attr)))
                break
        else:
            parts.append(str(entry))
    return "/".join(parts)


class Checkpointer:
    """Numbered checkpoints of one pytree under ``directory`` (keeps ``max_to_keep``).

    Args:
        directory: run checkpoint folder (created if missing).
        max_to_keep: how many most recent steps survive; ``None`` keeps all.
    """

    def __init__(self, directory: str | os.PathLike, max_to_keep: int | None = 3):
        if max_to_keep is not None and max_to_keep < 1:
            raise ValueError(f"max_to_keep must be >= 1 or None, got {max_to_keep}")
        self.directory = Path(directory).absolute()
        options = ocp.CheckpointManagerOptions(max_to_keep=max_to_keep, create=True)
        # Registering the handler up front lets a fresh manager (a new process) read the
        # stored metadata before any restore call names the args type.
        self._manager = ocp.CheckpointManager(
            self.directory,
            options=options,
            item_handlers=ocp.StandardCheckpointHandler(),
        )

    def save(self, step: int, pytree: Any, *, wait: bool = False) -> None:
        """Start saving ``pytree`` as checkpoint ``step`` (typed keys stored as data).

        Raises:
            ValueError: when ``step`` already exists in ``directory``.
        """
        if step in self._manager.all_steps():
            raise ValueError(
                f"checkpoint step {step} already exists in {self.directory}"
            )
        plain = jax.tree.map(
            lambda x: jax.random.key_data(x) if _is_typed_key(x) else x, pytree
        )
        self._manager.save(step, args=ocp.args.StandardSave(plain))
        if wait:
            self._manager.wait_until_finished()

    def all_steps(self) -> list[int]:
        """Saved steps in increasing order."""
        return sorted(self._manager.all_steps())

    def latest_step(self) -> int | None:
        """The newest saved step, or ``None`` when the directory holds none."""
        return self._manager.latest_step()

    def restore(self, step: int | None, abstract_pytree: Any) -> Any:
        """Restore checkpoint ``step`` (``None``: the latest) into the target structure.

        Args:
            step: saved step, or ``None`` for :meth:`latest_step`.
            abstract_pytree: target from ``jax.eval_shape`` (concrete arrays also work:
                only their structure, shapes and dtypes are used). Typed-key leaves
                are re-wrapped with the target's PRNG implementation.

        Returns:
            A pytree with the target's structure holding the stored values.

        Raises:
            FileNotFoundError: no such step.
            ValueError: stored structure or a leaf shape differs from the target.
        """
        if step is None:
            step = self.latest_step()
        if step is None or step not in self._manager.all_steps():
            raise FileNotFoundError(
                f"no checkpoint step {step} in {self.directory}; "
                f"saved: {self.all_steps()}"
            )
        abstract = jax.eval_shape(lambda t: t, abstract_pytree)
        plain_target = jax.tree.map(
            lambda x: jax.eval_shape(jax.random.key_data, x) if _is_typed_key(x) else x,
            abstract,
        )
        try:
            self._check_structure(step, plain_target)
            restored = self._manager.restore(
                step, args=ocp.args.StandardRestore(plain_target)
            )
        except ValueError as err:
            if str(err).startswith(f"checkpoint {self.directory}"):  # ours
                raise
            raise self._unreadable(step, err) from err
        except Exception as err:  # noqa: BLE001 - TensorStore / Orbax raise many
            raise self._unreadable(step, err) from err
        return jax.tree.map(
            lambda target, value: (
                jax.random.wrap_key_data(value, impl=_key_impl(target))
                if _is_typed_key(target)
                else value
            ),
            abstract,
            restored,
        )

    def _unreadable(self, step: int, err: Exception) -> ValueError:
        """The error of a checkpoint whose files cannot be read (a copy cut short,
        a disk that filled up): the folder, the file the reader named, the cause."""
        folder = self.directory / str(step)
        text = f"{type(err).__name__}: {err}"
        files = [p for p in folder.rglob("*") if p.is_file() and str(p.name) in text]
        named = f" (file {files[0]})" if files else ""
        return ValueError(
            f"checkpoint {folder}{named} is truncated or corrupt: it cannot be read "
            f"({_first_line(text)}). Copy the run folder again from its source, or "
            "train the run again"
        )

    def _check_structure(self, step: int, target: Any) -> None:
        """Raise a readable ``ValueError`` when ``target`` differs from the stored."""
        metadata = self._manager.item_metadata(step)
        stored_tree = getattr(metadata, "tree", metadata)
        stored = {
            _path_str(p): tuple(getattr(leaf, "shape", ()) or ())
            for p, leaf in jax.tree_util.tree_flatten_with_path(stored_tree)[0]
        }
        wanted = {
            _path_str(p): tuple(leaf.shape)
            for p, leaf in jax.tree_util.tree_flatten_with_path(target)[0]
        }
        missing = sorted(set(wanted) - set(stored))
        unexpected = sorted(set(stored) - set(wanted))
        reshaped = [
            f"{k}: stored {stored[k]}, target {wanted[k]}"
            for k in sorted(set(wanted) & set(stored))
            if stored[k] != wanted[k]
        ]
        if missing or unexpected or reshaped:
            raise ValueError(
                f"checkpoint {self.directory}/{step} does not match the target: "
                f"missing in checkpoint {missing}; not in target {unexpected}; "
                f"shape mismatches {reshaped}"
            )

    def wait_until_finished(self) -> None:
        """Block until pending asynchronous saves are on disk."""
        self._manager.wait_until_finished()

    def close(self) -> None:
        """Finish pending saves and release Orbax resources."""
        self._manager.wait_until_finished()
        self._manager.close()

    def __enter__(self) -> Checkpointer:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()


def _first_line(text: str, size: int = 300) -> str:
    line = text.strip().splitlines()[0] if text.strip() else text
    return line if len(line) <= size else line[: size - 3] + "..."


def save_config(run_dir: str | os.PathLike, cfg: Any) -> Path:
    """Write the resolved config as ``run_dir/config.json`` atomically.

    Args:
        run_dir: run folder (created if missing).
        cfg: a (nested) frozen dataclass config, or an already JSON-ready dict.

    Returns:
        The path written.
    """
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    data = cfg if isinstance(cfg, dict) else config_to_dict(cfg)
    text = json.dumps(to_json_value(data), indent=2) + "\n"
    return write_atomic(run_dir / CONFIG_FILE, text)


def load_config(run_dir: str | os.PathLike, cls: type | None = None) -> Any:
    """Read ``run_dir/config.json``: the raw dict, or an instance of ``cls`` if given.

    Raises:
        FileNotFoundError: the run has no config file.
        ValueError: the file does not describe a ``cls`` (see ``config_from_dict``).
    """
    path = Path(run_dir) / CONFIG_FILE
    if not path.is_file():
        raise FileNotFoundError(f"no {CONFIG_FILE} in {run_dir}")
    data = json.loads(path.read_text())
    return data if cls is None else config_from_dict(cls, data)
