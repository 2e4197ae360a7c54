"""What a diagnosis says: ``report.json``, ``report.md`` and figures (:mod:`.write`,
:mod:`.markdown`, :mod:`.formatting`), the verdict per unit (:mod:`.units`),
plausibility flags (:mod:`.plausibility`) and the extended model (:mod:`.extended`).
"""
