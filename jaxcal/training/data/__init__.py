"""What a training run reads: its file and splits (:mod:`.run`), any model's table
(:mod:`.tables`) or a model's own file as padded arrays (:mod:`.calibration`),
labelled units simulated from the model (:mod:`.simulated`, :mod:`.sim_paths`,
:mod:`.sim_effects`) and the units the policy trains on (:mod:`.train_env`).

:data:`MODEL_FILES` holds what a model brings, filled by the composition root
(:mod:`jaxcal`) with the turbofan's (:mod:`jaxcal.models.turbofan.training`):
``read(cfg, path, *, units, log, model)`` -> CalibrationData, or None for a table;
``generator(name)`` -> ``generate(path, progress)`` -> its summary line.
"""

MODEL_FILES: dict = {}
