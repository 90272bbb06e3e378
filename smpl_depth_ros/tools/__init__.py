"""Command-line tools: the demo, bag synthesis and playback, evaluation, sweeps, benchmarks and
the exporters of the shipped data files (each module has its own `main`)."""
