"""The benchmarks: one module per benchmark, each runnable from the repository root as
``python -m bench.NAME`` (``--help`` for its options), with a ``run(...)`` that returns its
result document and a ``main()`` that parses the arguments (``--json`` prints that document).
What they share (the live pipeline's start and stop, a service's URL, JSON writing) is in
:mod:`bench.common`; ``bench/docs.py`` renders ``results/`` into docs/measurements.md;
``bench/science.py`` is ``make science`` (its document is ``claims.json``, its page
docs/science.md); tests/unit/bench/test_bench_modules.py holds the others to this.
"""
