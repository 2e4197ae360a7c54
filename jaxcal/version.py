"""The package's version, in one leaf module: ``jaxcal.__version__`` re-exports it,
and a run folder records it (:mod:`jaxcal.training.model_source`) without importing
the package root, the top of the import graph."""

__version__ = "0.1.0"
