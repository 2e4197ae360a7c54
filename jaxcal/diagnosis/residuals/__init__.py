"""The residual and its noise: summaries of a normalised residual (:mod:`.summaries`),
the noise model, a level and an AR(p) colour per output (:mod:`.noise`), and its fit
(:mod:`.noise_fit`).
"""
