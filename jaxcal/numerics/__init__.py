"""Numerical cores shared by every layer above: they import nothing of jaxcal but
:mod:`jaxcal.typedefs`, so any module may use them (``tests/test_architecture.py``)."""
