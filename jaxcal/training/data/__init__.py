"""What a training run reads: its file and splits (:mod:`.run`), an N-CMAPSS-layout
file (:mod:`.ncmapss`) or any model's table (:mod:`.tables`) as padded arrays
(:mod:`.calibration`), labelled units simulated from the model (:mod:`.simulated`,
:mod:`.sim_paths`, :mod:`.sim_effects`) and the units the policy trains on
(:mod:`.train_env`).
"""
