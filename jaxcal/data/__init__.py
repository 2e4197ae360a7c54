"""jaxcal.data. :data:`FILE_READERS`: extension -> ``reader(path, *, nonfinite,
rename, **options) -> Dataset`` of the files that are not tables; the composition root
(:mod:`jaxcal`) registers the turbofan's (N-CMAPSS ``.h5``, C-MAPSS ``.txt``)."""

FILE_READERS: dict = {}
