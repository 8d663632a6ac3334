"""Declaring a problem: the problem-file schemas (translational, IMU and planar) and their
checks."""
