"""Matrices: loading and checking matrix files, planning episodes, running them locally or on Ray, and storing
results."""
