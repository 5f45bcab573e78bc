"""What users run: simulate, ensembles, basins, sweeps, the benchmark, and the configuration they share. Imports model, integrate and files."""
