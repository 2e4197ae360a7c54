"""The data as the diagnosis sees it: prepared rows and spline bases (:mod:`.prepare`,
:mod:`.loop_data`), wild readings left out (:mod:`.cleaning`), model evaluations
split over a cluster (:mod:`.sharding`), and synthetic data sets with one known
effect (:mod:`.synthetic`).
"""
