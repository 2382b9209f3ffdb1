"""Plain helpers every subsystem may use: atomic writes, content hashes and caches, locks,
ownership records, material names as file names, timing, checks of plain values, float32
weights without subnormal values (:mod:`.float32`), the process's peak memory (:mod:`.memory`),
worker processes that end with their parent (:mod:`.workers`) and what Ctrl-C does at each
stage of a process (:mod:`.interrupts`, the only module that installs a handler for it).

Imports nothing of the package but :mod:`mitsuba_manifold.errors` (and its own modules).
"""
