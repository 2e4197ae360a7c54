"""The turbofan, one model among others: :mod:`.model` (its Model, effects and fleet
defaults), ``physics/`` (the engine), ``data/`` (N-CMAPSS / C-MAPSS readers, writers
and the data-set generators), the fleet's stream (:mod:`.fleet`) and a training run's
data (:mod:`.training`). The core imports nothing from here
(``tests/test_architecture.py``)."""
