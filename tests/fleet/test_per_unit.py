"""``python -m jaxcal.fleet`` on an extended model whose offset some units carry.

The heat exchanger, 4 units of 60 rows, a +1 K step of the hot outlet thermometer
from row 20 in units 2 and 7 (of 2, 4, 7, 9: the carriers are not consecutive, so the
units stream in four runs). The exported model lists the carriers; the fleet command
line calibrates the offset in them and holds it at exactly 0 with std 0 elsewhere, as
``jaxcal.calibrate`` does, on one process and on two.
"""

import json
import os
import socket
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest

from jaxcal.cli.fleet import main
from jaxcal.fleet.per_unit import plan_runs
from jaxcal.fleet.results import read_results
from jaxcal.models import load

UNITS, ROWS, ONSET, STEP = (2, 4, 7, 9), 60, 20, 1.0
CARRIERS = (2, 7)
DECLARED = ("fouling", "heat_loss")
OFFSET = "T_hot_out_offset"
NOISE = {"T_hot_out": 0.05, "T_cold_out": 0.05, "dp_hot": 0.05, "duty": 0.5}
NOISE_ARG = "noise=" + ",".join(f"{k}:{v}" for k, v in NOISE.items())
TIMEOUT_S = 300


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _spec(units) -> dict:
    """An ``extended_model.json`` as the diagnosis writes it."""
    offset = {
        "name": OFFSET, "channel": "additive", "target": "T_hot_out",
        "nominal": 0.0, "low": -5.0, "high": 5.0, "unit": "K", "scale": 0.05,
        "units": units,
    }  # fmt: skip
    return {
        "format": "jaxcal.extended_model/1", "base": "heat_exchanger",
        "declared": list(DECLARED), "added": [offset],
    }  # fmt: skip


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    """``(folder, data path, carriers' model path, every unit's model path)``."""
    base = load("heat_exchanger")
    rng = np.random.default_rng(0)
    low, high = (np.asarray(b) for b in base.condition_range)
    n = len(UNITS) * ROWS
    w = rng.uniform(low, high, (n, len(low)))
    theta = np.tile(base.nominal, (n, 1))
    theta[:, 0] = np.repeat(0.05 * np.arange(len(UNITS)), ROWS)  # fouling per unit
    evaluate = jax.vmap(lambda w_t, th: base.evaluate(w_t, th)[0])
    x = np.asarray(evaluate(jnp.asarray(w), jnp.asarray(theta)))
    x = x + rng.normal(size=x.shape) * [NOISE[s] for s in base.output_names]
    unit, time = np.repeat(UNITS, ROWS), np.tile(np.arange(ROWS), len(UNITS))
    offset = STEP * (time >= ONSET) * np.isin(unit, CARRIERS)
    x[:, 0] += offset
    frame = pd.DataFrame(w, columns=base.condition_names)
    frame[list(base.output_names)] = x
    frame["unit"], frame["time"] = unit, time
    # the extended model's true parameters: theta_true in the file
    frame[list(DECLARED)] = theta[:, [base.parameter_names.index(p) for p in DECLARED]]
    frame[OFFSET] = offset
    folder = tmp_path_factory.mktemp("per_unit")
    data = folder / "hx.csv"
    frame.to_csv(data, index=False)
    paths = []
    for name, units in (("carriers", list(CARRIERS)), ("every", None)):
        paths.append(folder / f"{name}.json")
        paths[-1].write_text(json.dumps(_spec(units)))
    return folder, data, *paths


@pytest.fixture(scope="module")
def split_run(fleet, tmp_path_factory):
    """``(summary, arrays, attrs)`` of the UKF over the fleet with the carriers' model
    on one process (chunks of 2 units), run once: the per-unit checks and the
    two-process comparison read the same run."""
    import contextlib
    import io

    _, data, model_path, _ = fleet
    out = tmp_path_factory.mktemp("split") / "split.h5"
    argv = [f"model={model_path}", f"data={data}", "method=ukf", NOISE_ARG,
            "chunk_units=2", f"out={out}"]  # fmt: skip
    printed, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(printed), contextlib.redirect_stderr(err):
        code = main(argv)
    assert code == 0, err.getvalue()
    summary = json.loads(printed.getvalue().strip().splitlines()[-1])
    return (summary, *read_results(out))


def _run(argv, capsys) -> tuple[dict, dict, dict]:
    assert main(argv) == 0, capsys.readouterr().err
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    arrays, attrs = read_results(argv[-1].partition("=")[2])
    return summary, arrays, attrs


def test_runs_follow_the_units_and_their_carriers(fleet):
    _, _, model_path, every_path = fleet
    model = load(str(model_path))
    names = (*DECLARED, OFFSET)
    runs, note = plan_runs(model, names, np.asarray(UNITS), "ukf", {})
    assert [(r.unit_ids.tolist(), r.theta) for r in runs] == [
        ([2], names), ([4], DECLARED), ([7], names), ([9], DECLARED)
    ]  # fmt: skip
    assert note == (
        "per-unit parameters (the model's carriers): T_hot_out_offset held at "
        "nominal in unit(s) [4, 9]"
    )
    # the offset not calibrated, a policy (trained on every unit), no carriers: one run
    for args in ((DECLARED, "ukf"), (names, "policy")):
        assert plan_runs(model, args[0], np.asarray(UNITS), args[1], {})[1] is None
    every = load(str(every_path))
    assert plan_runs(every, names, np.asarray(UNITS), "ukf", {})[1] is None
    with pytest.raises(ValueError, match=r"unit\(s\) \[4, 9\] carry none"):
        plan_runs(model, (OFFSET,), np.asarray(UNITS), "ukf", {})


def test_non_carriers_hold_the_offset_at_zero_and_carriers_track_it(
    fleet, split_run, tmp_path, capsys
):
    folder, data, model_path, _ = fleet
    common = [f"data={data}", "method=ukf", NOISE_ARG, "chunk_units=2"]
    summary, got, attrs = split_run
    assert summary["theta_names"] == [*DECLARED, OFFSET]
    assert attrs["theta_names"] == [*DECLARED, OFFSET]
    assert summary["num_rows"] == len(UNITS) * ROWS and summary["num_units"] == 4
    assert summary["num_chunks"] == 4  # one per run: [2], [4], [7], [9]
    assert summary["notes"][0].endswith("held at nominal in unit(s) [4, 9]")
    assert attrs["unit_runs"] == summary["unit_runs"]
    assert attrs["notes"] == summary["notes"]
    np.testing.assert_array_equal(got["unit_id"], sorted(UNITS))  # the file's order
    np.testing.assert_array_equal(got["unit"], np.repeat(UNITS, ROWS))
    j = 2
    held = ~np.isin(got["unit"], CARRIERS)
    assert np.all(got["theta"][held, j] == 0.0)  # exactly: no effect
    assert np.all(got["aux_theta_std"][held, j] == 0.0)
    assert np.all(got["theta_true"][held, j] == 0.0)  # the truth, for theta_rmse
    for u in CARRIERS:  # the step tracked, within its reported std
        last = np.flatnonzero(got["unit"] == u)[-1]
        est, std = got["theta"][last, j], got["aux_theta_std"][last, j]
        assert 0.0 < std < 0.5 and abs(est - STEP) < 3 * std
    # each group as the same command on its own: the non-carriers as a run without
    # the offset, the carriers as a run with it (the same numbers, to round-off)
    _, clean, _ = _run(
        [f"model={model_path}", *common, f"theta={','.join(DECLARED)}",
         "units=4,9", f"out={tmp_path / 'clean.h5'}"], capsys,
    )  # fmt: skip
    np.testing.assert_allclose(got["theta"][held][:, :2], clean["theta"], atol=1e-12)
    np.testing.assert_allclose(
        got["aux_theta_std"][held][:, :2], clean["aux_theta_std"], atol=1e-12
    )
    _, carried, _ = _run(
        [f"model={model_path}", *common, "units=2,7", f"out={tmp_path / 'c.h5'}"],
        capsys,
    )
    np.testing.assert_allclose(got["theta"][~held], carried["theta"], atol=1e-12)
    # tracked in every unit (the export before), the clean units' offsets are not 0
    _, every, _ = _run(
        [f"model={fleet[3]}", *common, f"out={tmp_path / 'every.h5'}"], capsys
    )
    assert np.all(every["aux_theta_std"][held, j] > 0.0)
    assert np.any(every["theta"][held, j] != 0.0)


def test_two_processes_write_the_same_file(fleet, split_run, tmp_path):
    """The runs' collectives in the same order in both processes: the file equals
    one process's (the same command line, ``split_run``)."""
    _, data, model_path, _ = fleet
    args = [
        f"model={model_path}",
        f"data={data}",
        "method=ukf",
        NOISE_ARG,
        "chunk_units=2",
    ]
    a = split_run[1]
    argv = ["-m", "jaxcal.fleet", *args]
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    cluster = ["--coordinator", f"127.0.0.1:{free_port()}", "--num-processes", "2"]
    procs = [
        subprocess.Popen(
            [
                sys.executable,
                *argv,
                f"out={tmp_path / 'two.h5'}",
                *cluster,
                "--process-id",
                str(i),
            ],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )  # fmt: skip
        for i in range(2)
    ]
    for proc in procs:
        try:
            _, err = proc.communicate(timeout=TIMEOUT_S)
        except subprocess.TimeoutExpired:
            for other in procs:
                other.kill()
            raise
        assert proc.returncode == 0, err
    b, attrs = read_results(tmp_path / "two.h5")
    assert attrs["num_processes"] == 2
    assert sorted(a) == sorted(b)
    for name in a:
        np.testing.assert_allclose(b[name], a[name], atol=1e-12, err_msg=name)
    held = ~np.isin(b["unit"], CARRIERS)
    assert np.all(b["theta"][held, 2] == 0.0) and np.all(
        b["aux_theta_std"][held, 2] == 0
    )


def test_least_squares_and_the_covariance_hold_zero_rows(fleet, tmp_path, capsys):
    """Every per-parameter diagnostic of a held parameter is 0 (LS: its stds; the
    UKF's covariance: the parameter's row and column); a ``theta0`` of the held
    parameter does not move it off its nominal value."""
    _, data, model_path, _ = fleet
    common = [f"model={model_path}", f"data={data}", NOISE_ARG]
    _, ls, _ = _run(
        [*common, "method=ls", "window=4", "num_iters=2", f"out={tmp_path / 'ls.h5'}"],
        capsys,
    )
    held = ~np.isin(ls["unit"], CARRIERS)
    for name in ("theta", "aux_theta_std", "aux_laplace_std"):
        assert np.all(ls[name][held, 2] == 0.0), name
        assert np.all(ls[name][~held, 2] != 0.0), name
    _, ukf, _ = _run(
        [*common, "method=ukf", "return_cov=true", "theta0=0.1,0.02,0.5",
         f"out={tmp_path / 'cov.h5'}"], capsys,
    )  # fmt: skip
    cov = ukf["aux_theta_cov"]
    assert cov.shape == (len(UNITS) * ROWS, 3, 3)
    assert np.all(cov[held, 2, :] == 0.0) and np.all(cov[held, :, 2] == 0.0)
    assert np.all(cov[held][:, [0, 1], [0, 1]] > 0.0)  # the declared ones: tracked
    np.testing.assert_allclose(
        np.sqrt(cov[~held, 2, 2]), ukf["aux_theta_std"][~held, 2]
    )
    assert np.all(ukf["theta"][held, 2] == 0.0)  # theta0's 0.5: carriers' start only


def test_a_parameter_no_unit_of_a_group_carries_is_refused(fleet, tmp_path, capsys):
    _, data, model_path, _ = fleet
    argv = [
        f"model={model_path}", f"data={data}", NOISE_ARG, f"theta={OFFSET}",
        f"out={tmp_path / 'o.h5'}",
    ]  # fmt: skip
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "unit(s) [4, 9] carry none of these parameters" in err
    assert not (tmp_path / "o.h5").exists()


TOY_TURBOFAN = """
import jax.numpy as jnp
from jaxcal.model import Model


def toy(w, theta):
    tra = w[2] / 100
    hpt = theta[0]
    return jnp.stack([500 + 80 * tra - 900 * hpt, 1200 + 300 * tra - 700 * hpt])


MODEL = Model.from_function(
    toy, conditions=("alt", "Mach", "TRA", "T2"),
    parameters={"HPT_eff_mod": (0.0, -0.1, 0.03)}, outputs=("T24", "T30"),
    name="toy_turbofan", condition_range=([-1000, 0, 15, 400], [45000, 0.9, 105, 600]),
)
"""


def test_ncmapss_file_streams_the_carriers_runs(tmp_path, capsys):
    """An N-CMAPSS file (streamed, never read whole) with a T30 offset in unit 2 of
    1, 2, 3: the runs read only their units' rows."""
    from jaxcal.models.turbofan.data.ncmapss_io import write_ncmapss
    from jaxcal.models.turbofan.data.record import Record
    from jaxcal.models.turbofan.physics.constants import HEALTH_NAMES, SENSOR_NAMES

    (tmp_path / "toy.py").write_text(TOY_TURBOFAN)
    model = load(f"{tmp_path / 'toy.py'}:MODEL", trust_code=True)
    rng = np.random.default_rng(1)
    lengths, loss = [30, 40, 20], -0.01
    unit = np.repeat([1, 2, 3], lengths)
    n = unit.size
    w = rng.uniform([1e4, 0.3, 60, 480], [3e4, 0.7, 90, 520], (n, 4))
    theta = np.zeros((n, len(HEALTH_NAMES)))
    theta[:, HEALTH_NAMES.index("HPT_eff_mod")] = loss
    x = rng.normal(size=(n, len(SENSOR_NAMES))) + 500
    cols = [SENSOR_NAMES.index(s) for s in model.output_names]
    x[:, cols] = np.asarray(jax.vmap(model.evaluate)(w, np.full((n, 1), loss))[0])
    x[:, cols] += 0.05 * rng.normal(size=(n, len(cols)))
    step = (unit == 2) & (np.arange(n) - lengths[0] >= 10)
    x[step, SENSOR_NAMES.index("T30")] += 2.0
    rec = Record(
        w=w, x=x, x_names=SENSOR_NAMES, theta=theta, unit=unit,
        cycle=np.ones(n, int), flight_class=np.ones(n), hs=np.ones(n),
        rul=np.zeros(n, int),
    )  # fmt: skip
    data = tmp_path / "toy.h5"
    write_ncmapss(data, rec, rec)
    spec = {
        "format": "jaxcal.extended_model/1", "base": "toy.py:MODEL",
        "declared": ["HPT_eff_mod"],
        "added": [{
            "name": "T30_offset", "channel": "additive", "target": "T30",
            "nominal": 0.0, "low": -10.0, "high": 10.0, "unit": "K", "scale": 0.1,
            "units": [2],
        }],
    }  # fmt: skip
    (tmp_path / "ext.json").write_text(json.dumps(spec))
    summary, got, _ = _run(
        [f"model={tmp_path / 'ext.json'}", f"data={data}", "trust_code=true",
         "outputs=T24,T30", "noise=0.05", "split=dev", "chunk_units=2",
         f"out={tmp_path / 'out.h5'}"], capsys,
    )  # fmt: skip
    assert [r["units"] for r in summary["unit_runs"]] == [[1], [2], [3]]
    np.testing.assert_array_equal(got["unit_length"], lengths)
    np.testing.assert_array_equal(got["unit"], unit)
    held = got["unit"] != 2
    assert np.all(got["theta"][held, 1] == 0.0)
    assert np.all(got["aux_theta_std"][held, 1] == 0.0)
    last = np.flatnonzero(got["unit"] == 2)[-1]
    est, std = got["theta"][last, 1], got["aux_theta_std"][last, 1]
    assert 0.0 < std < 1.0 and abs(est - 2.0) < 3 * std
    np.testing.assert_allclose(got["unit_theta_last"][:, 0], loss, atol=2e-3)
