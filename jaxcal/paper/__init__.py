"""jaxcal.paper: every calibration method compared like for like (paper §5).

``methods`` builds UKF, least squares, E2E and trained policies behind the calibrator
interface (with the model perturbations of the robustness tables), ``compare`` runs
and scores them over whole test trajectories and measures their cost, ``simulate``
evaluates F in bulk (E2E-sim labels, E2E model outputs), ``suite`` holds one data set's
comparison, ``steps`` makes long experiments resumable, ``tables`` and ``report``
write ``REPORT.md`` beside the paper's numbers. ``experiments/paper.py`` runs it all.
"""
