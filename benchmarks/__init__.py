"""Speed measurements (:mod:`benchmarks.speed`) and experiments (:mod:`benchmarks.experiments`), run from the
repository root as modules, e.g. ``python -m benchmarks.speed.bench_operator --help``; see benchmarks/README.md."""
