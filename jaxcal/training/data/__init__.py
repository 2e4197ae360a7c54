"""What a training run reads: its file and splits (:mod:`.run`; a built-in model's
own files through :data:`jaxcal.models.TRAINING_FILES`), any model's table
(:mod:`.tables`) or a model's own file as padded arrays (:mod:`.calibration`),
labelled units simulated from the model (:mod:`.simulated`, :mod:`.sim_paths`,
:mod:`.sim_effects`) and the units the policy trains on (:mod:`.train_env`).
"""
