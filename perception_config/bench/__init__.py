"""Benchmarks that ship as commands: the blocks' timing and convergence, real photographs, the cell
simulation."""
