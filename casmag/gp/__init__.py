"""The Gaussian-process field: kernels, the reduced-rank (Hilbert-space) basis, the exact
prior, hyperparameter estimation and the map on a grid."""
