"""What a user runs: the command-line tools (:mod:`.cli`), the live explorer (:mod:`.explore`),
and the main job (:mod:`.pipeline`). The benchmarks (``tools/bench.py``) live outside the package,
in the repository's top-level ``benchmarks/``.

May import any subsystem; nothing in the library imports it.
"""
