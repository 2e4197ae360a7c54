"""How a training run scores its policy: the scores over whole unit trajectories
(:mod:`.trajectories`, :mod:`.policy`) and the run's ``final.json``
(:mod:`.final_report`).
"""
