"""The front door, :func:`jaxcal.calibrate` (:mod:`.door`): reading the call, screening
the data (:mod:`.screen`), per-row results (:mod:`.result`).
"""
