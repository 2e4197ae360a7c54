"""Names, units and physical constants shared by every layer of jaxcal.

This module owns the *vocabulary* of the project: the N-CMAPSS names of the operating
conditions ``W``, the health modifiers ``T`` and the sensors ``X_s`` / ``X_v``, plus the
C-MAPSS (2008) extra outputs. Everything is in the units of the N-CMAPSS files
(ft, -, %, degR, psia, rpm, lbm/s) so that our data and real NASA files mean the same
thing.
"""

from __future__ import annotations

# Operating conditions w, exactly N-CMAPSS ``W_var`` (ft, -, %, degR).
CONDITION_NAMES: tuple[str, ...] = ("alt", "Mach", "TRA", "T2")
CONDITION_UNITS: tuple[str, ...] = ("ft", "-", "%", "degR")

# Health modifiers theta, exactly N-CMAPSS ``T_var`` order.
# 0 = healthy, -0.01 = 1 % loss.
HEALTH_NAMES: tuple[str, ...] = (
    "fan_eff_mod",
    "fan_flow_mod",
    "LPC_eff_mod",
    "LPC_flow_mod",
    "HPC_eff_mod",
    "HPC_flow_mod",
    "HPT_eff_mod",
    "HPT_flow_mod",
    "LPT_eff_mod",
    "LPT_flow_mod",
)

# Measured sensors, exactly N-CMAPSS ``X_s_var`` order.
MEASURED_SENSOR_NAMES: tuple[str, ...] = (
    "T24", "T30", "T48", "T50", "P15", "P2", "P21", "P24", "Ps30", "P40", "P50",
    "Nf", "Nc", "Wf",
)  # fmt: skip
MEASURED_SENSOR_UNITS: tuple[str, ...] = (
    "degR", "degR", "degR", "degR", "psia", "psia", "psia", "psia", "psia", "psia",
    "psia", "rpm", "rpm", "lbm/s",
)  # fmt: skip

# Virtual sensors, exactly N-CMAPSS ``X_v_var`` order.
VIRTUAL_SENSOR_NAMES: tuple[str, ...] = (
    "T40", "P30", "P45", "W21", "W22", "W25", "W31", "W32", "W48", "W50",
    "SmFan", "SmLPC", "SmHPC", "phi",
)  # fmt: skip
VIRTUAL_SENSOR_UNITS: tuple[str, ...] = (
    "degR", "psia", "psia", "lbm/s", "lbm/s", "lbm/s", "lbm/s", "lbm/s", "lbm/s",
    "lbm/s", "-", "-", "-", "pps/psi",
)  # fmt: skip

# C-MAPSS (2008) outputs that N-CMAPSS files drop (epr = P50/P2, NRc uses T24).
EXTRA_SENSOR_NAMES: tuple[str, ...] = (
    "epr", "NRf", "NRc", "BPR", "farB", "PCNfR_dmd", "Nf_dmd",
)  # fmt: skip
EXTRA_SENSOR_UNITS: tuple[str, ...] = ("-", "rpm", "rpm", "-", "-", "%", "rpm")

SENSOR_NAMES: tuple[str, ...] = (
    MEASURED_SENSOR_NAMES + VIRTUAL_SENSOR_NAMES + EXTRA_SENSOR_NAMES
)
SENSOR_UNITS: tuple[str, ...] = (
    MEASURED_SENSOR_UNITS + VIRTUAL_SENSOR_UNITS + EXTRA_SENSOR_UNITS
)

# N-CMAPSS auxiliary columns ``A_var``.
AUX_NAMES: tuple[str, ...] = ("unit", "cycle", "Fc", "hs")

# Standard-day reference and unit constants (English units, as C-MAPSS).
T_STD_R = 518.67  # degR, ISA sea-level static temperature
P_STD_PSIA = 14.696  # psia, ISA sea-level static pressure
R_AIR_BTU = 0.068561  # BTU/(lbm degR) = 287.05 J/(kg K)
GC = 32.174  # lbm ft / (lbf s^2)
FT_LBF_PER_BTU = 778.169
HP_PER_BTU_S = 1.0 / 0.70679  # 1 BTU/s = 1.41485 hp
KJ_KG_K_PER_BTU_LBM_R = 4.1868  # 1 BTU/(lbm degR) = 4.1868 kJ/(kg K)
K_PER_R = 5.0 / 9.0


def sensor_index(names: tuple[str, ...] | list[str]) -> list[int]:
    """Indices of ``names`` in :data:`SENSOR_NAMES`, with a clear error for unknown
    ones.

    Args:
        names: sensor names, each one of :data:`SENSOR_NAMES`.

    Returns:
        The positions of the names in :data:`SENSOR_NAMES`.
    """
    unknown = [n for n in names if n not in SENSOR_NAMES]
    if unknown:
        raise ValueError(
            f"unknown sensor name(s) {unknown}; valid names are {list(SENSOR_NAMES)}"
        )
    return [SENSOR_NAMES.index(n) for n in names]


def health_index(names: tuple[str, ...] | list[str]) -> list[int]:
    """Indices of ``names`` in :data:`HEALTH_NAMES`, with a clear error for unknown
    ones."""
    unknown = [n for n in names if n not in HEALTH_NAMES]
    if unknown:
        raise ValueError(
            f"unknown health parameter(s) {unknown}; "
            f"valid names are {list(HEALTH_NAMES)}"
        )
    return [HEALTH_NAMES.index(n) for n in names]
