"""Honest uncertainty of the methods' estimates: split-conformal bands
(:mod:`.conformal`, :mod:`.std_scale`), the checks and widenings of a reported std
(:mod:`.jitter_check`, :mod:`.misfit_check`, :mod:`.lag_scale`, :mod:`.drift_std`).
"""
