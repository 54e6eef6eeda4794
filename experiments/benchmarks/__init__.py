"""Speed and memory benchmarks; each writes its table to ``experiments/results/``."""
