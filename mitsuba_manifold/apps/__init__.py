"""What a user runs: the command-line tools (:mod:`.cli`), the live explorer (:mod:`.explore`),
the benchmarks (:mod:`.bench`) and the main job (:mod:`.pipeline`).

May import any subsystem; nothing in the library imports it.
"""
