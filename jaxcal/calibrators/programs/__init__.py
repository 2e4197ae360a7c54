"""The calibrators' compiled programs: compiled once per process (:mod:`.compiled`),
kept on disk across processes (:mod:`.on_disk`, keyed by :mod:`.traced_key`), per-
row stream steps (:mod:`.packed`).
"""
