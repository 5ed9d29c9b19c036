"""Benchmarks: speed against same-run baselines (:mod:`.speed`) and the fault benchmark suites
(:mod:`.simulated`, :mod:`.independent`, :mod:`.robotino`). Nothing in the core imports this package."""
