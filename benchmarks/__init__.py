"""The benchmark suite: one script per question (docs/benchmarks.md); ``make bench`` runs it."""
