"""The training job of a tracking policy, and its configuration.

:mod:`~jaxcal.training.config` (with :mod:`~jaxcal.training.config_sections`) is the
typed, frozen configuration and its presets; :mod:`~jaxcal.training.pipeline` runs the
job (data -> surrogate D -> policy -> band -> test scores) through its stages
(``*_stage``; the policy's host loop and the policy it keeps in
:mod:`~jaxcal.training.kept_policy`), on the data of :mod:`~jaxcal.training.data.run`
(the :mod:`~jaxcal.training.data.calibration` records, read from an N-CMAPSS file by
:mod:`~jaxcal.models.turbofan.training` or from any model's rows by
:mod:`~jaxcal.training.data.tables`, with simulated units from
:mod:`~jaxcal.training.data.simulated`), the training environment of
:mod:`~jaxcal.training.data.train_env` and the machinery of
:mod:`~jaxcal.training.components` and :mod:`~jaxcal.training.runner`. A policy is
scored by :mod:`~jaxcal.training.scoring.policy` (with the scores of
:mod:`~jaxcal.training.scoring.trajectories`), and
the run's ``final.json`` is gathered by :mod:`~jaxcal.training.scoring.final_report`. A
run folder's own model is kept by :mod:`~jaxcal.training.model_source`. The files of a
run folder are :mod:`jaxcal.runs`'; reading a trained run back is the policy
method's (:mod:`jaxcal.calibrators.methods.policy.loading`: the config, runner,
components and model source sit at its layer, ``tests/test_architecture.py``).
"""
