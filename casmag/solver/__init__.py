"""Solving: the library entry points, warm starts (growing, sliding, several starts, sessions),
recordings and the Laplace uncertainty."""
