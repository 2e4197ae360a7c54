"""Reference numbers the engine model is fitted to and checked against.

Every number is derived from a named source (design/physics_facts.md, data_facts.md) so
that validation runs without the raw files. ``experiments/fit_engine_design.py``
recomputes the FD002 table from ``../shared/data/cmapss`` when the files are present and
checks it against these constants.
"""

from __future__ import annotations

import numpy as np

# FD002 operating conditions: mean op settings of the first 25 cycles of all 260
# training units, clustered by altitude (alt ft, Mach, TRA %, T2 degR = C-MAPSS s1).
FD002_CONDITIONS = np.array(
    [
        [0.0, 0.0, 100.0, 518.67],
        [10000.0, 0.25, 100.0, 489.05],
        [20000.0, 0.70, 100.0, 491.19],
        [25000.0, 0.62, 60.0, 462.54],
        [35000.0, 0.84, 100.0, 449.44],
        [42000.0, 0.84, 100.0, 445.00],
    ]
)

# Early-life means (first 25 cycles of every unit of train_FD002.txt), per condition.
# Derived here; physics_facts.md table 6.1 lists the same numbers rounded.
FD002_EARLY_MEANS: dict[str, list[float]] = {
    "T24": [642.34317, 604.61547, 607.29549, 536.69292, 555.52945, 549.45029],
    "T30": [1586.55151, 1498.48728, 1482.31853, 1259.9007, 1363.6497, 1351.23283],
    "T50": [1402.29002, 1305.48266, 1248.07815, 1046.01657, 1126.47273, 1122.63101],
    "P2": [14.62, 10.52, 9.35, 7.05, 5.48, 3.91],
    "P15": [21.6095, 15.49045, 13.65363, 9.02587, 8.0, 5.71405],
    "P30": [553.98662, 394.72344, 334.84571, 175.56918, 194.62643, 138.75563],
    "Nf": [2388.05853, 2318.8898, 2323.93868, 1915.33224, 2222.94249, 2211.89759],
    "Nc": [9055.06866, 8777.80889, 8722.40109, 8009.37123, 8349.18574, 8320.11411],
    "epr": [1.3, 1.26, 1.07922, 0.93998, 1.02057, 1.02001],
    "NRc": [8136.60172, 8130.32259, 8060.81213, 7873.69833, 8067.13791, 8083.84222],
    "BPR": [8.41725, 8.63848, 9.20634, 10.88222, 9.30632, 9.35304],
    "W31": [38.94066, 28.60573, 24.527, 14.30235, 14.87407, 10.6162],
    "W32": [23.35882, 17.16333, 14.71045, 8.58198, 8.92434, 6.36947],
    # C-MAPSS s11 * s12 / 3600: consistent with a fuel flow in lbm/s if s12 * s11 is
    # Wf in lbm/h (physics_facts.md 6.1 caveat); used only as a weak target.
    "Wf": [6.8643, 4.6791, 3.8768, 1.6769, 2.1283, 1.5237],
    # rounded in the files (0.03 / 0.02): a weak target
    "farB": [0.03, 0.03, 0.02025, 0.02, 0.02, 0.02],
}
# Within-condition standard deviation of the same rows (sensor noise + fleet spread).
FD002_EARLY_STD: dict[str, list[float]] = {
    "T24": [0.364, 0.3457, 0.3522, 0.3132, 0.3305, 0.3398],
    "T30": [4.4465, 4.386, 4.4983, 4.3305, 4.4854, 4.3968],
    "T50": [5.9282, 5.5942, 5.3916, 4.8294, 5.1193, 5.2065],
    "P30": [0.5977, 0.5108, 0.4617, 0.4171, 0.4276, 0.4068],
    "Nc": [8.4392, 8.1421, 7.5634, 6.4295, 7.493, 7.9652],
    "BPR": [0.0255, 0.025, 0.0269, 0.0267, 0.0271, 0.0266],
    "W31": [0.1232, 0.111, 0.1125, 0.1041, 0.1022, 0.101],
    "W32": [0.0776, 0.0673, 0.0681, 0.0613, 0.0617, 0.0629],
}
# The sensors of engine.md check 2 (median |error| <= 1 %, none over 3 %).
FD002_CHECKED_SENSORS = (
    "T24", "T30", "T50", "P15", "P30", "Nf", "Nc", "NRc", "epr", "BPR", "W31", "W32",
)  # fmt: skip

# FD001 (sea-level static, TRA 100) late-life minus early-life means: HPC degradation
# signature, engine.md check 3.
FD001_HPC_SIGNATURE: dict[str, float] = {
    "T24": 1.2, "T30": 14.0, "T50": 24.0, "P30": -2.4, "Nc": 40.0, "BPR": 0.1,
    "W31": -0.46,
}  # fmt: skip
FD001_CONDITION = np.array([0.0, 0.0, 100.0, 518.67])

# pyCycle CFM56-class cycle, HPT efficiency -1 % at fixed fan speed, mean over 27
# conditions (physics_facts.md 3.2 / 8): engine.md check 4 (within a factor of 2).
HPT_EFF_SIGNATURE: dict[str, float] = {
    "T48": 17.4,
    "T50": 13.4,
    "Nc": -23.0,
    "Wf_pct": 0.81,
}

# N-CMAPSS DS02 dev-set sensor ranges and flight envelope (data_facts.md 4).
DS02_ENVELOPE = {"alt": (10000.0, 35000.0), "Mach": (0.26, 0.75), "TRA": (24.0, 88.0)}
DS02_RANGES: dict[str, tuple[float, float]] = {
    "T48": (944.0, 1913.0),
    "T30": (1069.0, 1487.0),
    "Ps30": (80.0, 372.0),
    "Nf": (1470.0, 2263.0),
    "Nc": (7366.0, 8745.0),
    "Wf": (0.33, 4.54),
}

# AGTF30 steady-state operating points (physics_facts.md 6.3, NASA AGTF30 setup files).
# Conditions as (alt ft, Mach, corrected fan speed demand %, T2 degR).
AGTF30_POINTS = {
    "cruise": {
        "w": (35000.0, 0.8, 100.0, 444.6),
        "values": {
            "Nf": 2185.0, "Nc": 20796.0, "Wf": 0.7837, "W21": 815.5, "BPR": 23.2,
            "P2": 5.28, "P21": 6.86, "P24": 20.14, "Ps30": 270.8, "P50": 5.90,
            "T2": 444.6, "T24": 679.6, "T30": 1531.0, "T48": 2237.0,
        },
    },
    "takeoff_hot": {
        "w": (0.0, 0.0, 81.0, 545.7),
        "values": {
            "Nf": 1961.0, "Nc": 21583.0, "Wf": 1.3896, "W21": 1723.8, "BPR": 27.5,
            "P2": 14.62, "P21": 17.17, "P24": 42.24, "Ps30": 524.6, "P50": 16.78,
            "T2": 545.7, "T24": 758.4, "T30": 1632.0, "T48": 2258.0,
        },
    },
}  # fmt: skip
