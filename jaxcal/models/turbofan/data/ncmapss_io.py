"""Reading and writing the N-CMAPSS HDF5 layout (Arias Chao et al. 2021, NASA data set).

The layout is that of the real files (``N-CMAPSS_DS01-005.h5`` ...): per split ``dev`` /
``test`` the float64 datasets ``W_<split> [N, 4]``, ``X_s_<split> [N, 14]``,
``X_v_<split> [N, 14]``, ``T_<split> [N, 10]``, ``A_<split> [N, 4]`` (unit, cycle, Fc,
hs) and the int64 RUL ``Y_<split> [N, 1]``, plus fixed-width byte-string column names
``W_var``, ``X_s_var``, ``X_v_var``, ``T_var``, ``A_var`` (data_facts.md §2.1). Real
files have no root attributes and are sampled at 1 Hz; ours add ``sample_rate_hz`` (and
whatever ``attrs`` the caller passes, e.g. the generator config as JSON).

The reader never assumes a column order: it maps columns by the ``*_var`` names. Subsets
are read by slicing: selecting units scans only the unit column of ``A`` in blocks,
finds the contiguous row ranges of the wanted units, and reads only those rows, so a
unit of a 3 GB file costs about what its own rows cost. Writers are atomic: they fill a
temporary file in the destination directory and ``os.replace`` it into place only when
everything succeeded.
"""

from jaxcal.models.turbofan.data.ncmapss_layout import LAYOUT_NAMES, SPLITS
from jaxcal.models.turbofan.data.ncmapss_reader import load_ncmapss, ncmapss_info
from jaxcal.models.turbofan.data.ncmapss_writer import NCMAPSSWriter, write_ncmapss

__all__ = [
    "LAYOUT_NAMES",
    "SPLITS",
    "NCMAPSSWriter",
    "load_ncmapss",
    "ncmapss_info",
    "write_ncmapss",
]
