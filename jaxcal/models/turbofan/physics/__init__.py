"""The turbofan engine model: ``engine.load_engine(name).evaluate(w, theta) -> (x,
info)``; its modules are imported one by one (:mod:`.constants` alone costs nothing)."""
