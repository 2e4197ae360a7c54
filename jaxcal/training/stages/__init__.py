"""The stages of a training run (:mod:`jaxcal.training.pipeline`): the surrogate D
(:mod:`.surrogate`), the policy in jitted chunks (:mod:`.policy`), its tuning
through the deployed filter (:mod:`.tune`) and its uncertainty band
(:mod:`.uncertainty`).
"""
