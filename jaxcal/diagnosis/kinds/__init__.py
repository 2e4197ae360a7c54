"""The effects the diagnosis knows: the table of kinds and their candidates
(:mod:`.table`), what a fit moves (:mod:`.terms`), their signatures along the rows
(:mod:`.signatures`, :mod:`.linearization`) and a step's onset (:mod:`.onsets`).
"""
