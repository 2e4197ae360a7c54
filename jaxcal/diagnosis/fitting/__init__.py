"""Tracing the residual to the library: the joint Gauss-Newton fit (:mod:`.joint`), the
linearised screen (:mod:`.screen`), identification and ranking (:mod:`.identify`,
:mod:`.ranking`), and the discrepancy delta(w) when no effect explains it
(:mod:`.discrepancy`, :mod:`.fallback`).
"""
