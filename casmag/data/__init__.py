"""Data: simulated data sets and fields, recordings and real sequences, their plausibility
checks and clock."""
